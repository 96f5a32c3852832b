"""Progress of a batch: a bar with the rate and the time left on a terminal, plain log
lines elsewhere (a log file, a CI job), where a redrawn bar would be noise."""
from __future__ import annotations

import sys
import time

__all__ = ["Progress"]


def _duration(seconds: float) -> str:
    if seconds != seconds or seconds == float("inf"):
        return "?"
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


class Progress:
    """Counts finished jobs and shows them.

    Parameters
    ----------
    total : int
        Jobs to run (those skipped as done before are not counted).
    stream : file, optional
        Default ``sys.stderr``.
    bar : bool, optional
        Draw a bar; default: when `stream` is a terminal.
    every : float
        Seconds between log lines when there is no bar.
    enabled : bool
        False shows nothing.
    """

    def __init__(self, total: int, *, stream=None, bar: bool | None = None, every: float = 10.0,
                 enabled: bool = True):
        self.total = total
        self.stream = stream or sys.stderr
        self.bar = bar if bar is not None else bool(getattr(self.stream, "isatty", lambda: False)())
        self.every = every
        self.enabled = enabled
        self.done = 0
        self.failed = 0
        self.start = time.perf_counter()
        self._shown = 0.0

    def update(self, status: str) -> None:
        """One more job finished with `status` (``"done"`` or ``"failed"``)."""
        self.done += 1
        self.failed += status == "failed"
        now = time.perf_counter()
        # a bar redraws at most 5 times a second; log lines every `every` seconds and at the end
        if now - self._shown >= (0.2 if self.bar else self.every) or self.done == self.total:
            self._shown = now
            self._show(now)

    def rate(self) -> float:
        elapsed = time.perf_counter() - self.start
        return self.done / elapsed if elapsed > 0 else 0.0

    def _show(self, now: float) -> None:
        if not self.enabled:
            return
        elapsed = now - self.start
        rate = self.done / elapsed if elapsed > 0 else 0.0
        left = (self.total - self.done) / rate if rate > 0 else float("inf")
        failed = f", {self.failed} failed" if self.failed else ""
        if self.bar:
            width = 30
            filled = int(width * self.done / self.total) if self.total else width
            self.stream.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total}{failed} "
                              f"{rate:.2f} jobs/s, {_duration(left)} left ")
        else:
            self.stream.write(f"[{_duration(elapsed)}] {self.done}/{self.total} jobs{failed}, "
                              f"{rate:.2f} jobs/s, about {_duration(left)} left\n")
        self.stream.flush()

    def note(self, text: str) -> None:
        """A line of its own (what the engine is, a job skipped ...)."""
        if self.enabled:
            self.stream.write(text + "\n")
            self.stream.flush()

    def close(self) -> None:
        """End the bar's line."""
        if self.enabled and self.bar and self.done:
            self.stream.write("\n")
            self.stream.flush()
