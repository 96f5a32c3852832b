"""The commands' progress lines: one per finished step, with the time since the start."""
from __future__ import annotations

import time

__all__ = ["StepLog"]


class StepLog:
    """Call it with a message to print ``[   1.23 s] message`` (nothing when quiet), so
    long work shows where it is."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.start = time.perf_counter()

    def __call__(self, message: str) -> None:
        if not self.quiet:
            print(f"[{time.perf_counter() - self.start:7.2f} s] {message}", flush=True)
