"""Batches: expression transfer and template adaptation over a whole database, on Dask.

::

    jobs = tpscore.batch.transfer_jobs("bosphorus/", action_units=["12", "4"], pairs="next-2")
    report = tpscore.batch.run(jobs, "out/")            # a local cluster, one process per core
    print(report.summary())

The stages, one module each: :mod:`~tpscore.batch.jobs` (what a job is; jobs from a
Bosphorus-layout folder or a CSV manifest), :mod:`~tpscore.batch.work` (running one
job in a worker: cached inputs, the record), :mod:`~tpscore.batch.scores` (scores
against ``_gt.npz`` sidecars or a real scan), :mod:`~tpscore.batch.driver` (the Dask
driver), :mod:`~tpscore.batch.results` (the table and the summary) and
:mod:`~tpscore.batch.progress`. ``dask.distributed`` is imported only when a batch
runs.
"""
from __future__ import annotations

from .jobs import AdaptJob, Job, TransferJob, adapt_jobs, code_label, read_manifest, scan_layout, transfer_jobs
from .progress import Progress
from .results import STATUSES, BatchReport, read_table, write_table
from .driver import local_cluster, plan, run
from .scores import score_with_scan, score_with_sidecars
from .work import WorkSettings, execute

__all__ = ["run", "plan", "local_cluster", "execute", "WorkSettings", "Job", "TransferJob", "AdaptJob", "transfer_jobs",
           "adapt_jobs", "read_manifest", "scan_layout", "code_label", "BatchReport", "STATUSES",
           "read_table", "write_table", "Progress", "score_with_sidecars", "score_with_scan"]
