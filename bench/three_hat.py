"""The three-cornered hat: three measurements of one signal with independent errors, each one's quality.

When ``X_i = g_i s + e_i`` (one signal ``s``, gains ``g_i``, errors independent of ``s`` and of each other),
``cov(X_i, X_j) = g_i g_j var(s)`` for ``i != j``, so from the three pairwise covariances alone

- ``rho_i = sqrt(cov(X_i, X_j) cov(X_i, X_k) / cov(X_j, X_k)) / sd(X_i)`` is ``X_i``'s correlation with
  ``s``: against a reference ``X_j`` no measurement can reach a correlation above ``rho_j``;
- ``cov(X_i, X_k) / cov(X_j, X_k) = g_i / g_j``: ``X_i``'s gain in ``X_j``'s units, free of the attenuation
  that ``X_j``'s error puts on a least-squares slope of ``X_i`` on ``X_j`` (``rho_j² g_i / g_j``).

Used by ``bench/lid_brow_signals.py`` (track, dlib, MediaPipe) and ``bench/real_rig_fidelity.py`` (the rig
the judge scores, dlib, MediaPipe); tested in ``tests/test_three_hat.py``.
"""
from __future__ import annotations

import numpy as np


def common_signal(x: np.ndarray) -> dict[str, np.ndarray]:
    """``x`` (3, T): three series -> ``rho`` (3,), each one's correlation with their common signal (NaN where
    a covariance of the other two is not positive), and ``gain`` (3, 3), ``gain[i, j]`` = ``g_i / g_j`` from the
    third series (NaN where undefined)."""
    x = np.asarray(x, float)
    if x.ndim != 2 or x.shape[0] != 3:
        raise ValueError(f"expected three series, shape (3, T), got {x.shape}")
    c = np.cov(x)
    rho = np.full(3, np.nan)
    gain = np.full((3, 3), np.nan)
    for i in range(3):
        j, k = (m for m in range(3) if m != i)
        if c[j, k] > 0 and c[i, i] > 0:
            rho[i] = np.sqrt(max(c[i, j] * c[i, k] / c[j, k], 0.0) / c[i, i])
        gain[i, i] = 1.0
        for j in range(3):
            k = 3 - i - j
            if i != j and c[j, k] != 0:
                gain[i, j] = c[i, k] / c[j, k]
    return {"rho": rho, "gain": gain}
