"""The batch driver: jobs to Dask, records back, a results table out.

The engine is ``dask.distributed``: by default a local cluster with one worker process
per core, started and closed here; or an existing cluster (``scheduler="tcp://..."``,
or a ``Client``). The driver keeps a bounded number of jobs in flight and submits the
next as each finishes, so a batch of any size holds only that many futures, and what
comes back from a job is its small record: the arrays stay in the output files.

Nothing is lost: outputs and records are written atomically (a temporary file beside
them, then a rename), a rerun skips the jobs whose record and output are complete,
a job whose input is bad fails alone, a worker that dies mid-job has the job rerun
elsewhere by Dask, and Ctrl-C leaves complete outputs and a table of what is done.
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import time
from collections import Counter
from pathlib import Path

from .jobs import Job
from .progress import Progress
from .results import BatchReport, write_table
from .work import RECORDS_FOLDER, WorkSettings, execute, read_record

__all__ = ["run", "plan", "local_cluster", "local_cores"]

#: Seconds between rewrites of the results table while a batch runs, so that even a
#: client killed outright leaves a recent table (the records beside the outputs are
#: always current).
TABLE_EVERY_S = 60.0

#: Jobs in flight at least, whatever the worker count: each waits for a round trip
#: through the scheduler, and on a busy 2-core machine jobs that compute nothing ran at
#: 56 a second with 4 in flight, 81 with 64 and 142 with 512. A future holds a job's
#: description and, when done, its record: 64 of them cost the client little.
IN_FLIGHT_LEAST = 64

#: A temporary file younger than this is taken to be still in the writing (by a worker
#: of another run) and left alone when stale ones are cleaned up.
STALE_TEMPORARY_S = 60.0


def local_cores() -> int:
    """Cores this process may use (its CPU affinity, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _check_count(value, name: str, least: int):
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ValueError(f"{name} must be a whole number >= {least}, got {value!r}")
    return value


def plan(jobs, out, *, resume: bool = True) -> tuple[list[dict], list[Job]]:
    """Split jobs into those done by an earlier run and those to run.

    A job is done when its record says so, was made for the same job (its digest:
    inputs and options), and its output is the complete file the record describes.

    Returns
    -------
    skipped : list of dict
        The records of the done jobs, status ``"skipped"``.
    to_run : list of Job
    """
    skipped, to_run = [], []
    for job in jobs:
        record = read_record(out, job.name) if resume else None
        if (record is not None and record.get("status") == "done" and record.get("spec_hash") == job.spec_hash
                and job.output_complete(Path(out) / job.output_name, record)):
            skipped.append(dict(record, status="skipped"))
        else:
            to_run.append(job)
    return skipped, to_run


def _remove_temporaries(out: Path, older_than: float) -> None:
    """Remove the temporary files of interrupted writes (older than `older_than` s)."""
    now = time.time()
    for folder in (out, out / RECORDS_FOLDER):
        for path in folder.glob(".*.tmp"):
            try:
                if now - path.stat().st_mtime >= older_than:
                    path.unlink()
            except OSError:
                pass  # removed meanwhile, or not ours to remove


def _kernel_threads(client) -> tuple:
    """Kernel threads per host: the host's cores over the job threads on it, so that
    jobs running side by side do not oversubscribe the cores."""
    try:
        threads = client.nthreads()
        hosts = client.run(socket.gethostname)
        cores = client.run(local_cores)
    except Exception:  # noqa: BLE001 - a worker that cannot answer keeps its default
        return ()
    on_host, cores_of = Counter(), {}
    for address, count in threads.items():
        if address in hosts:
            on_host[hosts[address]] += count
            cores_of[hosts[address]] = cores.get(address, 1)
    return tuple(sorted((host, max(1, cores_of[host] // n)) for host, n in on_host.items()))


def _local_worker_plugin():
    """A plugin for the workers of the local cluster: Ctrl-C at a terminal signals the
    whole process group, workers included; the client alone should handle it (cancel,
    write the table, close the cluster), not every worker with a traceback. Defined
    here so that importing tpscore does not import Dask."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class IgnoreInterrupts(WorkerPlugin):
        name = "tpscore-batch-ignore-interrupts"

        def setup(self, worker):
            # the worker's event loop runs in its process's main thread, where signal
            # handlers are set; a restarted worker gets the plugin again
            signal.signal(signal.SIGINT, signal.SIG_IGN)

    return IgnoreInterrupts()


def local_cluster(workers: int):
    """The local cluster a batch starts: `workers` single-threaded worker processes
    (the jobs are Python-heavy: threads of one process would share its GIL), and a
    client connected to it. Returns (cluster, client); close both.

    Two of Dask's defaults are changed for these workers. Its ``MALLOC_TRIM_THRESHOLD_``
    (which hands freed memory back to the system at once) is not set: it also stops
    glibc from raising its mmap threshold, so every large NumPy temporary is mapped and
    unmapped afresh, which made a transfer and its scoring about twice as slow in a
    worker as in a plain process. And the workers ignore Ctrl-C (see
    :func:`_local_worker_plugin`).
    """
    import dask
    from distributed import Client, LocalCluster

    _check_count(workers, "workers", 1)
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=logging.ERROR)
    try:
        client = Client(cluster)
        client.register_plugin(_local_worker_plugin())
    except BaseException:
        cluster.close()
        raise
    return cluster, client


def _not_run_row(job: Job) -> dict:
    return dict(name=job.name, kind=job.kind, status="not run", error="", **job.columns())


def _failed_row(job: Job, exc: BaseException) -> dict:
    text = " ".join(str(exc).split()) or "no message"
    return dict(name=job.name, kind=job.kind, status="failed", error=f"{type(exc).__name__}: {text}",
                **job.columns())


def run(jobs, out, *, scheduler: str | None = None, client=None, workers: int | None = None,
        resume: bool = True, gt_faces=None, truth: bool = False, cache_scans: int = 8, retries: int = 2,
        max_in_flight: int | None = None, progress: bool | Progress = True, table: str = "results") -> BatchReport:
    """Run jobs on Dask and write their outputs, records and a results table.

    Parameters
    ----------
    jobs : iterable of Job
        From :func:`transfer_jobs`, :func:`adapt_jobs`, :func:`read_manifest`, or made
        directly; names must be unique.
    out : path
        The output folder (made if missing): ``<name>.npz`` / ``<name>.obj`` per job,
        ``records/<name>.json`` per finished job, ``<table>.csv`` (and ``.parquet``).
        On a cluster, every worker must see it (and the inputs) at the same path.
    scheduler : str, optional
        Address of a running Dask scheduler (``"tcp://host:8786"``). Default: a local
        cluster of `workers` processes, started and closed here.
    client : distributed.Client, optional
        An existing client to use (and leave open) instead.
    workers : int, optional
        Worker processes of the local cluster; default one per core.
    resume : bool
        Skip jobs done by an earlier run into the same folder.
    gt_faces : path, optional
        ``.npz`` with ``faces``: the triangles of the ``_gt.npz`` sidecars' meshes; with
        it, transfers whose target scans have sidecars are scored exactly.
    truth : bool
        Score the other transfers against the target's own scan of the expression
        (surface distances: lower bounds).
    cache_scans : int
        Scans each worker keeps between jobs.
    retries : int
        Reruns of a job that raised an error of the machine (``OSError``,
        ``MemoryError``); a job whose worker dies is rerun by Dask's own rule (up to
        three deaths by default).
    max_in_flight : int, optional
        Jobs submitted and not yet finished: the client holds that many futures, never
        more. Default four per worker thread, at least 64 (enough to keep every worker
        busy while results come back).
    progress : bool or Progress
        Show progress on stderr (a bar on a terminal, log lines otherwise).
    table : str
        Stem of the results table in `out`.

    Returns
    -------
    BatchReport
        ``interrupted`` is True when Ctrl-C stopped the run: the table then lists the
        jobs not run, and a rerun resumes.

    Raises
    ------
    ValueError
        Duplicate job names, a bad argument, `out` not a folder, `gt_faces` missing.
    """
    start = time.perf_counter()
    jobs, out, gt_faces = _checked_run(jobs, out, scheduler, client, workers, cache_scans, retries, max_in_flight,
                                       gt_faces)
    (out / RECORDS_FOLDER).mkdir(parents=True, exist_ok=True)
    _remove_temporaries(out, STALE_TEMPORARY_S)

    skipped, to_run = plan(jobs, out, resume=resume)
    rows = {row["name"]: row for row in skipped}
    meter = progress if isinstance(progress, Progress) else Progress(len(to_run), enabled=bool(progress))
    report = BatchReport([], out)
    own_cluster = own_client = None
    try:
        if to_run:
            client, own_cluster, own_client = _connect(client, scheduler, workers)
            report.startup_seconds = time.perf_counter() - start
            threads = client.nthreads()
            report.workers = len(threads)
            meter.note(f"{len(skipped)} jobs done before, {len(to_run)} to run on "
                       f"{'a local cluster' if own_cluster else client.scheduler.address} of {len(threads)} "
                       f"worker(s), {sum(threads.values())} thread(s) (ready in {report.startup_seconds:.1f} s)")
            settings = WorkSettings(str(out), gt_faces, bool(truth), cache_scans, _kernel_threads(client))
            limit = max_in_flight or max(IN_FLIGHT_LEAST, 4 * sum(threads.values()))
            report.interrupted = not _stream(client, to_run, settings, limit, retries, rows, meter,
                                             lambda: write_table([rows.get(j.name) or _not_run_row(j) for j in jobs],
                                                                 out / table))
            meter.close()
    finally:
        if own_client is not None:
            own_client.close()
        if own_cluster is not None:
            own_cluster.close()
    if report.interrupted and own_cluster is not None:
        # the local workers are gone: what they were writing is no output
        _remove_temporaries(out, 0.0)
    if report.interrupted:
        # jobs that finished while the interrupt was handled have their records
        late, _ = plan([job for job in jobs if job.name not in rows], out)
        rows.update((row["name"], dict(row, status="done")) for row in late)
    report.rows = [rows.get(job.name) or _not_run_row(job) for job in jobs]
    report.seconds = time.perf_counter() - start
    report.tables = write_table(report.rows, out / table)
    return report


def _checked_run(jobs, out, scheduler, client, workers, cache_scans, retries, max_in_flight, gt_faces):
    """The run's arguments checked: the jobs as a list, the output folder and the
    sidecars' faces as absolute paths."""
    jobs = list(jobs)
    bad = [type(j).__name__ for j in jobs if not isinstance(j, Job)]
    if bad:
        raise ValueError(f"jobs must be Job objects (TransferJob, AdaptJob), got {bad[0]}")
    names = Counter(job.name for job in jobs)
    duplicates = sorted(name for name, count in names.items() if count > 1)
    if duplicates:
        raise ValueError(f"jobs: names must be unique, {len(duplicates)} repeat ({', '.join(duplicates[:3])})")
    _check_count(workers, "workers", 1)
    _check_count(cache_scans, "cache_scans", 1)
    _check_count(retries, "retries", 0)
    _check_count(max_in_flight, "max_in_flight", 1)
    if scheduler is not None and client is not None:
        raise ValueError("give scheduler or client, not both")
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise ValueError(f"out: {str(out)!r} is a file, not a folder")
    if gt_faces is not None:
        gt_faces = os.path.abspath(gt_faces)
        if not os.path.isfile(gt_faces):
            raise ValueError(f"gt_faces: {gt_faces!r}: file not found")
    return jobs, out, gt_faces


def _connect(client, scheduler, workers):
    """The client to run on: the caller's, one of a scheduler's, or one of a local
    cluster started here. Returns (client, the cluster and the client to close)."""
    from distributed import Client

    if client is not None:
        return client, None, None
    if scheduler is not None:
        client = Client(scheduler)
        return client, None, client
    cluster, client = local_cluster(workers or local_cores())
    return client, cluster, client


def _stream(client, to_run, settings, limit, retries, rows, meter, write_progress_table) -> bool:
    """Submit the jobs, at most ``limit`` in flight, and record each row as its job
    finishes (the table rewritten every TABLE_EVERY_S). Returns False when Ctrl-C
    stopped it (the jobs in flight are then cancelled)."""
    from distributed import as_completed

    in_flight: dict = {}
    pending = iter(to_run)
    # results come with the futures, fetched on the client's event loop as the futures
    # finish, rather than one blocking round trip per job here
    completed = as_completed(with_results=True, raise_errors=False)

    def submit_next() -> None:
        job = next(pending, None)
        if job is not None:
            future = client.submit(execute, job, settings, retries=retries, pure=False,
                                   key=f"tpscore-batch-{job.name}-{job.spec_hash}")
            in_flight[future.key] = (future, job)
            completed.add(future)

    try:
        meter.start = time.perf_counter()
        for _ in range(limit):
            submit_next()
        written = time.perf_counter()
        for future, result in completed:
            _, job = in_flight.pop(future.key)
            if future.status == "finished":
                row = result
            else:  # the task raised (an error of the machine, retries spent; a worker died
                # each time it ran the job): the job's failure, not the batch's
                row = _failed_row(job, result[1] if isinstance(result, tuple) else result)
            future.release()
            rows[job.name] = row
            meter.update(row["status"])
            submit_next()
            if time.perf_counter() - written > TABLE_EVERY_S:
                written = time.perf_counter()
                write_progress_table()
    except KeyboardInterrupt:
        if in_flight:
            client.cancel([future for future, _ in in_flight.values()])
        return False
    return True
