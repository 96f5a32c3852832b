"""Throughput, overhead and memory of tpscore.batch on a local Dask cluster.

Three measurements, each against a plain Python loop over the same jobs in this
process (``tpscore.batch.execute``: the same work, the same scan cache, no engine):

1. **transfers**: default-pipeline transfers of make_scans.py scans (150 x 150, colour
   images), with 1 and 2 worker processes: jobs per second, and the engine's cost
   per job (the 1-worker batch's time over the loop's, per job). The outputs of the
   batch are checked equal to the loop's, bit for bit.
2. **empty jobs**: jobs that compute nothing (each still writes its record): what the
   engine itself costs per job, and how many jobs a second it can hand out.
3. **memory**: a few thousand small jobs (the method as published on a 64 x 64 grid)
   on 2 workers: the resident memory of the client (which also hosts the local
   cluster's scheduler) and of each worker, sampled as the batch goes, to show that
   neither grows with the number of jobs.

    python benchmarks/batch_throughput.py [--subjects 4] [--repeats 2] [--empty 2000] [--small 2000]

Writes bench-output/batch_throughput.md and prints it. Skips (exit 0) without
../shared (make_scans.py and the ICT face model; set TPSCORE_SHARED).
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import psutil

from shared_data import shared_dir
from report import write_report

from tpscore import batch
from tpscore.batch import Job, Progress
from tpscore.batch.jobs import transfer_options
from tpscore.batch.work import WorkSettings

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class EmptyJob(Job):
    """A job that computes nothing and writes no output: what is left is the engine
    (submission, scheduling, the task's round trip) and the job's record."""

    name: str
    kind: ClassVar[str] = "empty"
    save: ClassVar[bool] = False

    def columns(self) -> dict:
        return {}

    def run(self, context) -> dict:
        return {}

    def output_complete(self, path, record) -> bool:
        return True


class MemorySampler(Progress):
    """Samples the resident memory of this process and of every worker as jobs finish."""

    def __init__(self, total, client, every):
        super().__init__(total, enabled=False)
        self.client = client
        self.sample_every = every
        self.samples = []  # (jobs finished, client MB, [worker MB])

    def sample(self):
        workers = self.client.run(lambda: psutil.Process().memory_info().rss)
        self.samples.append((self.done, psutil.Process().memory_info().rss / 2**20,
                             sorted(v / 2**20 for v in workers.values())))

    def update(self, status):
        super().update(status)
        if self.done % self.sample_every == 0 or self.done == self.total:
            self.sample()


def _generate(shared: Path, folder: Path, subjects, codes, *extra) -> None:
    if not all((folder / f"bs{s:03d}" / f"bs{s:03d}_{codes[-1]}_gt.npz").is_file() for s in subjects):
        subprocess.run([sys.executable, str(shared / "tools" / "make_scans.py"), str(folder), "--subjects",
                        *map(str, subjects), "--expressions", *codes, *extra], check=True, stdout=subprocess.DEVNULL)


def _loop(jobs, out: Path) -> tuple[float, float]:
    """(seconds, CPU seconds) of the plain loop over the jobs in this process."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    settings = WorkSettings(str(out))
    start, cpu = time.perf_counter(), time.process_time()
    for job in jobs:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            record = batch.execute(job, settings)
        assert record["status"] == "done", record["error"]
    return time.perf_counter() - start, time.process_time() - cpu


def _cluster(workers: int):
    """The local cluster tpscore.batch.run starts, started here so that the memory
    sampler can ask its workers."""
    start = time.perf_counter()
    cluster, client = batch.local_cluster(workers)
    return cluster, client, time.perf_counter() - start


def _cpu_seconds() -> float:
    times = psutil.Process().cpu_times()
    return times.user + times.system


def _batch(jobs, out: Path, workers: int, client_hook=None):
    """(seconds of the batch on a started cluster, seconds to start the cluster, report,
    the progress hook, CPU seconds of this process (client and scheduler) and of the
    workers during the batch)."""
    shutil.rmtree(out, ignore_errors=True)
    cluster, client, startup = _cluster(workers)
    try:
        meter = client_hook(client) if client_hook else False
        workers_before = sum(client.run(_cpu_seconds).values())
        client_before = _cpu_seconds()
        start = time.perf_counter()
        report = batch.run(jobs, out, client=client, progress=meter)
        seconds = time.perf_counter() - start
        client_cpu = _cpu_seconds() - client_before
        workers_cpu = sum(client.run(_cpu_seconds).values()) - workers_before
    finally:
        client.close()
        cluster.close()
    assert report.counts()["done"] == len(jobs), report.summary()
    return seconds, startup, report, meter, (client_cpu, workers_cpu)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=4, help="subjects of the transfer scans (default 4)")
    ap.add_argument("--empty", type=int, default=2000, help="empty jobs (default 2000)")
    ap.add_argument("--small", type=int, default=2000, help="small jobs of the memory run (default 2000)")
    ap.add_argument("--repeats", type=int, default=2, help="runs of each transfer configuration (default 2)")
    ap.add_argument("--out", default=str(ROOT / "bench-output"))
    args = ap.parse_args(argv)
    shared = shared_dir()
    if shared is None:
        print("batch benchmark skipped: ../shared (make_scans.py, the ICT face model) not found")
        return 0
    out = Path(args.out)
    work = out / "batch-runs"
    lines = [f"# tpscore.batch throughput ({os.cpu_count()} cores; load average at the start "
             f"{os.getloadavg()[0]:.1f})", ""]

    # 1. transfers: every ordered pair of subjects, two AUs; each run twice, in turn,
    # and the faster kept (other work on the machine comes and goes)
    scans = out / "batch-scans"
    subjects = list(range(args.subjects))
    _generate(shared, scans, subjects, ["N_N_0", "UFAU_1_0", "LFAU_12_0"])
    jobs = batch.transfer_jobs(scans, pairs="all")
    n = len(jobs)
    best = {}
    for _ in range(args.repeats):
        seconds, cpu = _loop(jobs, work / "loop")
        best["loop"] = min(best.get("loop", (np.inf,)), (seconds, None, cpu / n))
        for workers in (1, 2):
            seconds, startup, report, _, (client_cpu, workers_cpu) = _batch(jobs, work / f"transfers-{workers}",
                                                                             workers)
            best[workers] = min(best.get(workers, (np.inf,)), (seconds, startup, (client_cpu + workers_cpu) / n))
            for job in jobs:
                with np.load(work / "loop" / f"{job.name}.npz") as a, \
                        np.load(work / f"transfers-{workers}" / f"{job.name}.npz") as b:
                    assert np.array_equal(a["vertices"], b["vertices"], equal_nan=True), job.name
    loop = best["loop"][0]
    lines += [f"## Transfers (load average {os.getloadavg()[0]:.1f} at the end): {n} default-pipeline transfers ({args.subjects} subjects, every ordered pair, "
              "AU1 and AU12; 150 x 150, colour images); outputs equal to the loop's, bit for bit; "
              f"the faster of {args.repeats} runs", "",
              "| run | engine start s | batch s | jobs/s | s per job | CPU s per job | vs loop |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    for name, key in (("plain loop (this process)", "loop"), ("batch, 1 worker", 1), ("batch, 2 workers", 2)):
        seconds, startup, cpu = best[key]
        lines.append(f"| {name} | {'' if startup is None else f'{startup:.1f}'} | {seconds:.1f} | "
                     f"{n / seconds:.2f} | {seconds / n:.3f} | {cpu:.3f} | {loop / seconds:.2f}x |")
    one = best[1][0]
    lines += ["", f"Engine cost per transfer with 1 worker: ({one:.1f} - {loop:.1f}) s / {n} = "
              f"{(one - loop) / n * 1e3:.0f} ms (this includes the worker's first import of tpscore and "
              "its own cold scan cache). CPU s per job: the CPU time of this process (the loop; or the "
              "client with the local cluster's scheduler) and of the workers over the run, per job; unlike "
              "the wall time, it does not depend on what else runs on the machine.", ""]

    # 2. empty jobs
    empty = [EmptyJob(f"empty{i:06d}") for i in range(args.empty)]
    loop, loop_cpu = _loop(empty, work / "empty-loop")
    rows = [("plain loop (this process)", loop, None, (loop_cpu, 0.0))]
    for workers in (1, 2):
        seconds, startup, _, _, cpu = _batch(empty, work / f"empty-{workers}", workers)
        rows.append((f"batch, {workers} worker(s)", seconds, startup, cpu))
    m = args.empty
    lines += [f"## Empty jobs (load average {os.getloadavg()[0]:.1f} at the end): {m} jobs that compute nothing (each writes its record)", "",
              "| run | engine start s | batch s | jobs/s | ms per job | CPU ms per job: client + scheduler | "
              "CPU ms per job: workers |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, seconds, startup, (client_cpu, workers_cpu) in rows:
        lines.append(f"| {name} | {'' if startup is None else f'{startup:.1f}'} | {seconds:.1f} | "
                     f"{m / seconds:.0f} | {seconds / m * 1e3:.2f} | {client_cpu / m * 1e3:.2f} | "
                     f"{workers_cpu / m * 1e3:.2f} |")
    one_cpu = sum(rows[1][3]) / m * 1e3
    lines += ["", f"The engine's own cost per job with 1 worker: {(rows[1][1] - loop) / m * 1e3:.2f} ms of wall "
              f"time over the loop's, {one_cpu - loop_cpu / m * 1e3:.2f} ms of CPU time (client, scheduler and "
              "worker together, over the loop's); the CPU time does not depend on what else runs on the "
              "machine, the wall time does.", ""]

    # 3. memory on a few thousand small jobs
    small_scans = out / "batch-scans-small"
    _generate(shared, small_scans, [0, 1, 2], ["N_N_0", "LFAU_12_0"], "--texture-scale", "0")
    base = batch.transfer_jobs(small_scans, pairs="all", grid=(64, 64), options=transfer_options("published"))
    small = [batch.TransferJob(f"{job.name}_{k:05d}", job.source_neutral, job.source_expressive, job.target,
                               job.action_units, job.magnitude, job.options, job.grid, truth=job.truth)
             for k in range(-(-args.small // len(base))) for job in base][: args.small]
    seconds, startup, report, sampler, _ = _batch(small, work / "small", 2,
                                               client_hook=lambda c: MemorySampler(len(small), c, len(small) // 10))
    samples = sampler.samples
    lines += [f"## Memory: {len(small)} small jobs (the method as published, 64 x 64 grid) on 2 workers", "",
              f"{len(small) / seconds:.1f} jobs/s; resident memory as the batch goes (MB; the client process "
              "also hosts the local cluster's scheduler):", "",
              "| jobs finished | client | worker 1 | worker 2 |", "|---:|---:|---:|---:|"]
    for done, client_mb, workers_mb in samples:
        lines.append(f"| {done} | {client_mb:.0f} | " + " | ".join(f"{w:.0f}" for w in workers_mb) + " |")
    growth = samples[-1][1] - samples[0][1]
    lines += ["", f"Client growth from the first sample to the last: {growth:+.0f} MB over "
              f"{samples[-1][0] - samples[0][0]} jobs. Load average at the end {os.getloadavg()[0]:.1f}."]

    table = "\n".join(lines)
    write_report(out / "batch_throughput.md", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
