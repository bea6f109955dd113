"""Held-back evaluation frames for the labelling benchmarks and their tests (bench/bench_label_eval.py,
bench/synth3d_tracker_diag.py)."""
from __future__ import annotations

import numpy as np

from keyshape.base.errors import InputError


def spread_frames(n_frames: int, count: int, exclude=(), min_gap: int = 12, rng=None) -> np.ndarray:
    """``count`` frames drawn at random, spread over the video, ``min_gap`` away from ``exclude``.

    For held-back evaluation frames: random rather than chosen for variety, so
    they sample the performance as it is. The video is cut into ``count`` equal
    spans and one frame drawn in each (retrying spans that fall too close).
    """
    g = np.random.default_rng(rng)
    taken = [int(e) for e in exclude]
    edges = np.linspace(0, n_frames, count + 1).astype(int)
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        ok = np.arange(a, b)
        if taken or out:
            ref = np.array(taken + out)
            ok = ok[np.min(np.abs(ok[:, None] - ref[None]), axis=1) >= min_gap]
        if not len(ok):
            raise InputError(f"cannot place {count} held-back frames {min_gap} apart in {n_frames} frames")
        out.append(int(g.choice(ok)))
    return np.array(out, dtype=np.intp)
