"""Shared benchmark reporting.

Benchmarks of one kernel share a pytest-benchmark group; the benchmark whose name
contains "tpscore" is the baseline, and at the end of the run every other member of
the group is reported as a speed ratio against it (ratio > 1: tpscore is faster),
using the minimum time of each (the least noisy statistic on a shared machine).
The table is printed and written to bench-output/ratios.md.
"""
from __future__ import annotations

import os
from collections import defaultdict

import pytest

OUTPUT_DIR = os.environ.get("TPSCORE_BENCH_OUT", os.path.join(os.path.dirname(__file__), "..", "bench-output"))


def _ratio_rows(benchmarks):
    groups = defaultdict(list)
    for bench in benchmarks:
        if bench.stats is None or not getattr(bench.stats, "rounds", 0):
            continue
        groups[bench.group or bench.name].append(bench)
    rows = []
    for group, members in sorted(groups.items()):
        base = [b for b in members if "tpscore" in b.name]
        if not base:
            continue
        base_min = base[0].stats.min
        for bench in members:
            if bench is base[0]:
                continue
            rows.append((group, bench.name, base_min, bench.stats.min, bench.stats.min / base_min))
    return rows


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    session = getattr(config, "_benchmarksession", None)
    if session is None or not session.benchmarks:
        return
    rows = _ratio_rows(session.benchmarks)
    if not rows:
        return
    lines = [
        "| group | compared with | tpscore min | other min | speed-up |",
        "|---|---|---:|---:|---:|",
    ]
    for group, name, base, other, ratio in rows:
        short = name.split("[")[0].replace("test_", "")
        lines.append(f"| {group} | {short} | {base * 1e3:.3f} ms | {other * 1e3:.3f} ms | {ratio:.1f}x |")
    text = "\n".join(lines)
    terminalreporter.write_sep("=", "tpscore speed-up (other min / tpscore min)")
    terminalreporter.write_line(text)
    os.makedirs(OUTPUT_DIR, exist_ok=True)
    with open(os.path.join(OUTPUT_DIR, "ratios.md"), "w") as fh:
        fh.write(text + "\n")


def pytest_collection_modifyitems(config, items):
    # Benchmarks are never silently skipped as "tests": make a disabled run explicit.
    if config.getoption("benchmark_disable", False):
        for item in items:
            item.add_marker(pytest.mark.skip(reason="benchmarks disabled"))
