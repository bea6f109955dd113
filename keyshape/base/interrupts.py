"""Threads that Ctrl-C and SIGTERM cannot wedge: a bounded hand-over, and a thread start.

Design notes and figures: docs/reliability.md, "Notes on the code", ``keyshape/base/interrupts.py``.
"""
from __future__ import annotations

import contextlib
import queue
import signal
import threading
from typing import Any, Iterator

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM until the block ends, then act on the first as before the block.

    For short stretches of code that must not be interrupted half-way (a lock taken and not
    released); in another thread than the main one (where signals are not handled) it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list = []

    def hold(signum, frame):
        pending.append((signum, frame))

    old = {s: signal.signal(s, hold) for s in _SIGNALS}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if pending:
            signum, frame = pending[0]
            handler = old[signum]
            if callable(handler):
                handler(signum, frame)          # KeyboardInterrupt, or keyshape's Terminated
            elif handler == signal.SIG_DFL:
                signal.raise_signal(signum)


def start_thread(thread: threading.Thread) -> None:
    """``thread.start()`` with Ctrl-C and SIGTERM held until it has started (:func:`deferred_interrupts`)."""
    with deferred_interrupts():
        thread.start()


class Handoff:
    """Hand items from one thread to another, at most ``size`` waiting.

    Parameters
    ----------
    size : how many items may wait before :meth:`put` blocks (>= 1)
    poll : seconds between a blocked :meth:`put`'s checks for :meth:`close`
    """

    def __init__(self, size: int, poll: float = 0.05):
        if size < 1:
            raise ValueError(f"size {size}: need at least 1")
        self._items: queue.SimpleQueue = queue.SimpleQueue()
        self._free: queue.SimpleQueue = queue.SimpleQueue()
        for _ in range(size):
            self._free.put(None)
        self.poll = poll
        self.closed = False

    def put(self, item: Any) -> bool:
        """Add ``item``, waiting while ``size`` items wait; False (``item`` dropped) once closed."""
        while not self.closed:
            try:
                self._free.get(timeout=self.poll)
            except queue.Empty:
                continue
            if self.closed:                     # woken by close()
                return False
            self._items.put(item)
            return True
        return False

    def get(self, timeout: float | None = None) -> Any:
        """The next item, waiting for one (``queue.Empty`` after ``timeout`` seconds, if given)."""
        item = self._items.get(timeout=timeout)
        self._free.put(None)
        return item

    def close(self) -> None:
        """Stop: a :meth:`put` waiting for room (woken at once), and every later one, returns False."""
        self.closed = True
        self._free.put(None)
