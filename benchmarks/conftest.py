"""Shared benchmark reporting.

Benchmarks of one kernel share a pytest-benchmark group; the benchmark whose name
contains "tpscore" is the baseline, and at the end of the run every other member of
the group is reported as a speed ratio against it (ratio > 1: tpscore is faster),
using the minimum time of each (the least noisy statistic on a shared machine).

Benchmarks may also record, in ``benchmark.extra_info``, the flops they perform
("flops") or, for the machine's peak, the flops of a reference computation
("peak_flops"); each benchmark with "flops" is then reported against its arithmetic
limit, flops / (peak_flops / that benchmark's minimum time), from the same run.

The tables are printed and written to bench-output/ratios.md, headed by the machine,
the instruction set the kernels ran (``TPSCORE_SIMD`` lowers it) and the date; a run at
a set below the CPU's best writes bench-output/ratios-<set>.md instead, so that
``make bench`` keeps one table per instruction set the CPU offers.
"""
from __future__ import annotations

import datetime
import os
import platform
from collections import defaultdict

import pytest

OUTPUT_DIR = os.environ.get("TPSCORE_BENCH_OUT", os.path.join(os.path.dirname(__file__), "..", "bench-output"))


def _measured(benchmarks):
    return [b for b in benchmarks if b.stats is not None and getattr(b.stats, "rounds", 0)]


def _short(name):
    return name.split("[")[0].replace("test_", "")


def _ratio_rows(benchmarks):
    groups = defaultdict(list)
    for bench in _measured(benchmarks):
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


def _limit_lines(benchmarks):
    measured = _measured(benchmarks)
    peaks = [b for b in measured if "peak_flops" in b.extra_info]
    with_flops = [b for b in measured if "flops" in b.extra_info]
    if not peaks or not with_flops:
        return []
    peak = max(b.extra_info["peak_flops"] / b.stats.min for b in peaks)
    # OpenBLAS picks its kernels from the CPU whatever NumPy's switches say;
    # OPENBLAS_CORETYPE (make bench sets it with TPSCORE_SIMD) holds it to the same set
    core = os.environ.get("OPENBLAS_CORETYPE")
    lines = [
        "",
        f"Arithmetic limits: the measured peak is {peak / 1e9:.0f} GFlop/s (a float64 matrix "
        f"product, OpenBLAS through NumPy{f' with its {core} kernels' if core else ''}, all threads, "
        "fastest round); limit = the benchmark's flops / that peak.",
        "",
        "| benchmark | flops | limit | tpscore min | tpscore / limit |",
        "|---|---:|---:|---:|---:|",
    ]
    for bench in sorted(with_flops, key=lambda b: b.group or b.name):
        limit = bench.extra_info["flops"] / peak
        lines.append(f"| {bench.group or bench.name} | {bench.extra_info['flops']:.3g} | "
                     f"{limit * 1e3:.3f} ms | {bench.stats.min * 1e3:.3f} ms | "
                     f"{bench.stats.min / limit:.1f}x |")
    return lines


def _machine_line(session):
    try:
        info = session.get_machine_info()  # pytest-benchmark's (py-cpuinfo's) view
    except Exception:  # an older pytest-benchmark: fall back to the platform module
        info = {}
    cpu = info.get("cpu", {}) if isinstance(info, dict) else {}
    brand = cpu.get("brand_raw") or platform.processor() or platform.machine()
    count = cpu.get("count") or os.cpu_count()
    flags = set(cpu.get("flags", []))
    simd = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "no AVX2"
    return (f"Machine: {brand}, {count} logical CPUs, {simd}; kernels at {_kernel_level()}"
            f"{' (set by TPSCORE_SIMD)' if _lowered() else ''}, NumPy's disabled features: "
            f"{os.environ.get('NPY_DISABLE_CPU_FEATURES') or 'none'}; Python {platform.python_version()}; "
            f"run {datetime.date.today().isoformat()}.")


def _kernel_level() -> str:
    """The instruction set the compiled kernels run: the CPU's best, or lower by TPSCORE_SIMD."""
    from tpscore import _core
    return _core.simd_level()


def _lowered() -> bool:
    """Whether TPSCORE_SIMD chose the level (the run then writes a table of its own)."""
    return bool(os.environ.get("TPSCORE_SIMD"))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    session = getattr(config, "_benchmarksession", None)
    if session is None or not session.benchmarks:
        return
    rows = _ratio_rows(session.benchmarks)
    if not rows:
        return
    lines = [
        _machine_line(session),
        "",
        "| group | compared with | tpscore min | other min | speed-up |",
        "|---|---|---:|---:|---:|",
    ]
    for group, name, base, other, ratio in rows:
        lines.append(f"| {group} | {_short(name)} | {base * 1e3:.3f} ms | {other * 1e3:.3f} ms | {ratio:.1f}x |")
    lines += _limit_lines(session.benchmarks)
    text = "\n".join(lines)
    terminalreporter.write_sep("=", "tpscore speed-up (other min / tpscore min)")
    terminalreporter.write_line(text)
    os.makedirs(OUTPUT_DIR, exist_ok=True)
    name = f"ratios-{_kernel_level()}.md" if _lowered() else "ratios.md"
    with open(os.path.join(OUTPUT_DIR, name), "w") as fh:
        fh.write(text + "\n")


def pytest_collection_modifyitems(config, items):
    # Benchmarks are never silently skipped as "tests": make a disabled run explicit.
    if config.getoption("benchmark_disable", False):
        for item in items:
            item.add_marker(pytest.mark.skip(reason="benchmarks disabled"))
