"""Optional temporal smoothing of tracked landmarks (off by default).

``savgol`` (a centred Savitzky-Golay filter, zero lag, delaying the output stream by two frames) or ``oneeuro``
(Casiraghi, Roussel & Vogel 2012, causal); never across a lost frame (NaN). docs/tracker.md, ``--smooth``.
"""
from __future__ import annotations

import numpy as np

from keyshape.base.errors import InputError

METHODS = ("none", "savgol", "oneeuro")


class StreamSmoother:
    """Smooth landmarks frame by frame (memory bounded by the window, not the video).

    ``push(points, payload)`` returns the list of ``(smoothed_points, payload)``
    now ready (the payload, e.g. the frame and its pose, travels with its
    points); ``flush()`` returns the rest at the end of the stream.

    Parameters
    ----------
    method : ``none``, ``savgol`` or ``oneeuro``
    fps : float
        Frame rate (the one-euro filter works in pixels per second).
    window, order : int
        Savitzky-Golay window (odd) and polynomial order.
    min_cutoff, beta : float
        One-euro parameters: cut-off at rest (Hz) and its growth with speed.
    """

    def __init__(self, method: str = "none", fps: float = 30.0, window: int = 5, order: int = 2,
                 min_cutoff: float = 1.5, beta: float = 0.3):
        if method not in METHODS:
            raise InputError(f"unknown smoothing {method!r}: use one of {', '.join(METHODS)}")
        self.method, self.fps, self.half, self.order = method, float(fps), window // 2, order
        self.min_cutoff, self.beta = min_cutoff, beta
        self._items: dict[int, tuple] = {}
        self._n_in = self._n_out = 0
        self._prev = self._dprev = None

    def push(self, points: np.ndarray, payload=None) -> list:
        pts = np.asarray(points, np.float64)
        if self.method == "none":
            return [(pts, payload)]
        if self.method == "oneeuro":
            return [(self._euro(pts), payload)]
        self._items[self._n_in] = (pts, payload)
        self._n_in += 1
        out = []
        while self._n_out + self.half < self._n_in:
            out.append(self._emit())
        return out

    def flush(self) -> list:
        out = []
        while self._n_out < self._n_in:
            out.append(self._emit())
        return out

    def _emit(self):
        c = self._n_out
        self._n_out += 1
        out = self._fit(c)
        self._items.pop(c - self.half, None)
        return out

    def _fit(self, c: int):
        centre, payload = self._items[c]
        if not np.isfinite(centre).all():
            return centre, payload
        lo = hi = c
        while lo > c - self.half and lo - 1 in self._items and np.isfinite(self._items[lo - 1][0]).all():
            lo -= 1
        while hi < c + self.half and hi + 1 in self._items and np.isfinite(self._items[hi + 1][0]).all():
            hi += 1
        if hi - lo + 1 <= self.order:
            return centre, payload
        t = np.arange(lo, hi + 1, dtype=np.float64) - c
        w = np.linalg.pinv(np.vander(t, self.order + 1))[-1]   # weights giving the fit's value at t = 0
        y = np.stack([self._items[k][0] if k != c else centre for k in range(lo, hi + 1)])
        return np.tensordot(w, y, axes=1), payload

    def _euro(self, x: np.ndarray) -> np.ndarray:
        if not np.isfinite(x).all():
            self._prev = self._dprev = None
            return x
        if self._prev is None:
            self._prev, self._dprev = x, np.zeros_like(x)
            return x
        dt = 1.0 / self.fps

        def alpha(cut):
            return 1.0 / (1.0 + 1.0 / (2 * np.pi * cut * dt))

        dx = (x - self._prev) / dt
        ad = alpha(1.0)
        self._dprev = ad * dx + (1 - ad) * self._dprev
        a = alpha(self.min_cutoff + self.beta * np.abs(self._dprev))
        self._prev = a * x + (1 - a) * self._prev
        return self._prev

