"""A small progress reporter for long runs (frames per second, ETA).

It writes to standard error: a self-overwriting line on a terminal, and a
line every ``every`` seconds otherwise (CI logs stay short).
"""
from __future__ import annotations

import sys
import time


class Progress:
    """Count items done and report the rate.

    Parameters
    ----------
    total : int or None
        Expected number of items (None when unknown, e.g. a stream).
    desc : str
        Label printed before the counts.
    unit : str
        Name of one item ("frames").
    enabled : bool
        False silences it (library use, tests).
    every : float
        Seconds between reports when standard error is not a terminal.
    min_seconds : float
        Report nothing until this many seconds have passed (quick runs stay silent).
    """

    def __init__(self, total: int | None = None, desc: str = "", unit: str = "frames",
                 enabled: bool = True, every: float = 5.0, min_seconds: float = 0.0):
        self.total, self.desc, self.unit, self.enabled, self.every = total, desc, unit, enabled, every
        self.min_seconds = min_seconds
        self._shown = False
        self.n = 0
        self.start = time.perf_counter()
        self._last = 0.0
        self._tty = sys.stderr.isatty()

    @property
    def rate(self) -> float:
        """Items per second so far."""
        dt = time.perf_counter() - self.start
        return self.n / dt if dt > 0 else 0.0

    def update(self, n: int = 1) -> None:
        self.n += n
        if not self.enabled:
            return
        now = time.perf_counter()
        if now - self.start < self.min_seconds:
            return
        if now - self._last >= (0.2 if self._tty else self.every):
            self._last = now
            self._print(end="\r" if self._tty else "\n")

    def _print(self, end: str) -> None:
        self._shown = True
        tot = f"/{self.total}" if self.total else ""
        pct = f" {100.0 * self.n / self.total:5.1f}%" if self.total else ""
        eta = ""
        if self.total and self.rate > 0:
            eta = f", {max(self.total - self.n, 0) / self.rate:5.1f} s left"
        sys.stderr.write(f"{self.desc}: {self.n}{tot} {self.unit}{pct} ({self.rate:.1f} {self.unit}/s{eta})   {end}")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled and (self._shown or self.min_seconds <= 0):
            self._print(end="\n")

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
