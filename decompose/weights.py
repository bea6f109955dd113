"""Blend weights of key shapes for every frame: least squares, NNLS (eq. 4) and smoothed NNLS.

Section 4.1 of 004_119ba07521a9af0b.txt. Each frame ``Q_t`` is written as a
linear morph of the key shapes (eq. 3). Shapes are taken relative to a
``neutral`` shape (the mean of the sequence, as the paper's PCA centres them),
so a frame is ``Q_t = neutral + sum_i w_ti (S_i - neutral)``; pass
``neutral=None`` for the paper's literal absolute form ``Q_t = sum_i w_ti S_i``.

All solvers are vectorised over frames. The key basis ``B`` (n_keys, d) is
reduced once to its Gram matrix ``G = B B^T = R^T R`` (``R`` from the QR factor
of ``B^T``) and every frame is projected with one matrix product ``h = X B^T``;
the per-frame problem ``min_w ||B^T w - x||^2`` is then the k-sized
``min_w w^T G w - 2 h^T w`` (the same minimiser, the constant ``||x||^2`` dropped).
"""
from __future__ import annotations

import numpy as np
import os

from scipy.fft import dct, idct
from scipy.linalg import cho_solve_banded, cholesky_banded

from keyshape.base.errors import InputError

_WORKERS = max(1, min(4, os.cpu_count() or 1))  # scipy.fft threads for the smoothed solver's DCTs


# --------------------------------------------------------------------------- helpers

def _flatten(shapes: np.ndarray, keys: np.ndarray, neutral: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Return X (n_frames, d) and B (n_keys, d), both relative to ``neutral`` where given."""
    shapes = np.asarray(shapes, dtype=np.float64)
    keys = np.asarray(keys, dtype=np.float64)
    if shapes.ndim != 3 or keys.ndim != 3 or shapes.shape[1:] != keys.shape[1:]:
        raise InputError(f"shapes (n_frames, n_points, dim) and keys (n_keys, n_points, dim) must agree: "
                         f"got {shapes.shape} and {keys.shape}")
    if len(keys) == 0:
        raise InputError("no key shapes given")
    if not np.isfinite(keys).all():
        raise InputError("key shapes contain NaN or infinite values")
    if not np.isfinite(shapes).all():
        bad = np.flatnonzero(~np.isfinite(shapes).all(axis=(1, 2)))
        raise InputError(f"shapes contain NaN or infinite values at frame rows {bad[:5].tolist()}"
                         f"{'...' if len(bad) > 5 else ''}: mark those frames failed (success=0) instead")
    if neutral is not None:
        neutral = np.asarray(neutral, dtype=np.float64)
        if neutral.shape != shapes.shape[1:]:
            raise InputError(f"neutral: expected shape {shapes.shape[1:]}, got {neutral.shape}")
        shapes = shapes - neutral
        keys = keys - neutral
    return shapes.reshape(len(shapes), -1), keys.reshape(len(keys), -1)


def _gram(B: np.ndarray) -> np.ndarray:
    """``R^T R`` from the QR factor of ``B^T`` (d, n_keys): the Gram matrix of the key basis."""
    if B.shape[0] <= B.shape[1]:
        r = np.linalg.qr(B.T, mode="r")
        return r.T @ r
    return B @ B.T


def reconstruct(weights: np.ndarray, keys: np.ndarray, neutral: np.ndarray | None = None) -> np.ndarray:
    """Eq. (3): ``neutral + sum_i w_i (S_i - neutral)`` for every frame; (n_frames, n_points, dim)."""
    keys = np.asarray(keys, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    if neutral is None:
        return np.einsum("tk,kpd->tpd", w, keys)
    neutral = np.asarray(neutral, dtype=np.float64)
    return neutral + np.einsum("tk,kpd->tpd", w, keys - neutral)


# --------------------------------------------------------------------------- least squares

def lstsq_weights(shapes: np.ndarray, keys: np.ndarray, neutral: np.ndarray | None = None,
                  ridge: float = 0.0) -> np.ndarray:
    """Unconstrained least-squares weights (eq. 3 in the least-squares sense): the paper's bad example.

    Returns (n_frames, n_keys); weights may be large and of both signs. ``ridge`` > 0 adds the
    Tikhonov term of :func:`nnls_weights` (ridge regression).
    """
    X, B = _flatten(shapes, keys, neutral)
    if ridge == 0:
        return np.linalg.lstsq(B.T, X.T, rcond=None)[0].T
    return np.linalg.solve(_ridged(_gram(B), ridge), B @ X.T).T


# --------------------------------------------------------------------------- NNLS

def _masked_solve(G: np.ndarray, h: np.ndarray, passive: np.ndarray) -> np.ndarray:
    """Solve ``G_PP w_P = h_P`` for every row's passive set P (w = 0 elsewhere), batched.

    ``G`` (k, k) or (m, k, k), ``h`` (m, k), ``passive`` (m, k) bool. Rows of the system
    outside P are replaced by identity rows so one batched ``np.linalg.solve`` does all frames.
    """
    p = passive.astype(np.float64)
    A = (G if G.ndim == 3 else G[None]) * (p[:, :, None] * p[:, None, :])
    idx = np.arange(G.shape[-1])
    A[:, idx, idx] += 1.0 - p
    return np.linalg.solve(A, (h * p)[..., None])[..., 0]


def nnls_gram(G: np.ndarray, h: np.ndarray, max_iter: int | None = None, tol: float = 1e-10,
              passive: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact NNLS ``min_{w >= 0} w^T G w - 2 h^T w`` for many right-hand sides at once.

    Block principal pivoting (Kim and Park 2011), an active-set method like
    Lawson-Hanson's that exchanges every infeasible variable at once and falls
    back to exchanging one (the largest index) when that stops reducing their
    number; it ends at the point satisfying the KKT conditions ``w >= 0``,
    ``y = G w - h >= 0``, ``w * y = 0``: the unique NNLS solution for
    positive-definite ``G``, the one Lawson-Hanson (eq. 4, [Law74]) finds.

    Parameters
    ----------
    G : (n_keys, n_keys) or (m, n_keys, n_keys)
        Positive definite Gram matrix ``B B^T`` (one shared, or one per problem).
    h : (m, n_keys)
        Projections ``X B^T``.
    max_iter : int, optional
        Pivoting iterations (default ``10 * n_keys``).
    tol : float
        Relative feasibility tolerance.
    passive : (m, n_keys) bool, optional
        Initial guess of the positive weights (warm start); default: those
        positive in the unconstrained solution.

    Returns
    -------
    w : (m, n_keys) non-negative weights.
    converged : (m,) bool.
    """
    G = np.asarray(G, dtype=np.float64)
    h = np.atleast_2d(np.asarray(h, dtype=np.float64))
    m, k = h.shape
    batched = G.ndim == 3
    max_iter = 10 * k if max_iter is None else max_iter
    scale = max(float(np.abs(np.diagonal(G, axis1=-2, axis2=-1)).max()), 1e-300)
    Gs = G / scale + np.eye(k) * 1e-13  # ridge guards exactly collinear keys; far below any meaningful weight
    hs = h / scale
    htol = tol * max(1.0, float(np.abs(hs).max(initial=0.0)))
    if passive is None:
        passive = np.linalg.solve(Gs, hs[..., None])[..., 0] > 0 if batched else np.linalg.solve(Gs, hs.T).T > 0
    passive = np.array(passive, dtype=bool)
    w = np.zeros((m, k))
    converged = np.zeros(m, dtype=bool)
    n_bad_best = np.full(m, k + 1)
    backup = np.full(m, 3)
    todo = np.arange(m)
    for _ in range(max_iter):
        if not len(todo):
            break
        P = passive[todo]
        Gt = Gs[todo] if batched else Gs
        x = _masked_solve(Gt, hs[todo], P)
        y = (np.einsum("mij,mj->mi", Gt, x) if batched else x @ Gs) - hs[todo]
        infeasible = (P & (x < -htol)) | (~P & (y < -htol))
        n_bad = infeasible.sum(axis=1)
        done = n_bad == 0
        w[todo[done]] = np.where(P[done], np.maximum(x[done], 0.0), 0.0)
        converged[todo[done]] = True
        # exchange all infeasible variables while their count falls (or for 3 tries), else only one
        better = n_bad < n_bad_best[todo]
        n_bad_best[todo[better]] = n_bad[better]
        backup[todo[better]] = 3
        full = better | (backup[todo] > 0)
        backup[todo[~better & full]] -= 1
        last = k - 1 - np.argmax(infeasible[:, ::-1], axis=1)
        single = np.zeros_like(infeasible)
        single[np.arange(len(todo)), last] = True
        passive[todo] = P ^ np.where(full[:, None], infeasible, single)
        todo = todo[~done]
    if len(todo):  # not converged: best feasible point of the last passive set
        x = _masked_solve(Gs[todo] if batched else Gs, hs[todo], passive[todo])
        w[todo] = np.maximum(x, 0.0) * passive[todo]
    return w, converged


def _ridged(G: np.ndarray, ridge: float) -> np.ndarray:
    """``G + ridge * (trace(G) / k) * I``: the Tikhonov term ``ridge * s * ||w||^2`` with ``s`` the
    mean key shape's squared size, so ``ridge`` is dimensionless (0 = the paper's eq. 4)."""
    if not (np.isfinite(ridge) and ridge >= 0):
        raise InputError(f"ridge must be a non-negative number, got {ridge}")
    if ridge == 0:
        return G
    return G + ridge * float(np.trace(G)) / len(G) * np.eye(len(G))


def nnls_weights(shapes: np.ndarray, keys: np.ndarray, neutral: np.ndarray | None = None,
                 return_converged: bool = False, ridge: float = 0.0):
    """Non-negative least-squares weights, eq. (4) of 004_119ba07521a9af0b.txt, for all frames at once.

    ``min_{w_t >= 0} ||Q_t - neutral - sum_i w_ti (S_i - neutral)||^2`` for each frame ``t``.
    The key basis is factored once (QR -> Gram ``R^T R``), all frames are projected
    with one product, and the k-sized problems are solved together by
    :func:`nnls_gram`; the result equals ``scipy.optimize.nnls`` frame by frame.

    Parameters
    ----------
    shapes : (n_frames, n_points, dim)
    keys : (n_keys, n_points, dim)
    neutral : (n_points, dim) or None
    return_converged : bool
        Also return the per-frame convergence flags.
    ridge : float
        Optional Tikhonov term ``ridge * (trace(G) / n_keys) * ||w_t||^2`` added to eq. (4)
        (0, the default, is the paper's NNLS). Tracked shapes carry noise, and NNLS explains
        it with extra weight on keys whose 2D deltas are small; a 3D target face shows those
        weights as exaggerated expressions (depth motion the 2D contours hardly see). In
        ``keyshape demo`` (20 labels, greedy k=8) ridge 0.03 lowers the target-face vertex
        error from 1.08 to 0.68 mm. Where targets are exactly the 2D key shapes (the toy
        tracks of ``decompose.toy``) it only adds bias: leave it at 0 there.

    Returns
    -------
    (n_frames, n_keys) weights, never negative (and the flags if asked).
    """
    X, B = _flatten(shapes, keys, neutral)
    G = _ridged(_gram(B), ridge)
    w, ok = nnls_gram(G, X @ B.T)
    return (w, ok) if return_converged else w


# --------------------------------------------------------------------------- smoothed NNLS

def smooth_weights(shapes: np.ndarray, keys: np.ndarray, neutral: np.ndarray | None = None,
                   smooth_lambda: float = 0.1, observed: np.ndarray | None = None,
                   max_iter: int = 3000, tol: float = 1e-5, return_info: bool = False, ridge: float = 0.0):
    """NNLS over the whole sequence with a penalty on frame-to-frame weight change, as one QP.

    Solves ``min_{W >= 0} sum_t m_t ||B^T w_t - x_t||^2 + mu sum_t ||w_t - w_{t-1}||^2`` with
    ``mu = smooth_lambda * trace(G) / n_keys`` (so ``smooth_lambda`` is dimensionless: 1 means
    a unit weight step costs as much as the mean key shape's squared size), ``m_t`` = 1 for
    observed frames and 0 for failed ones (whose weights the penalty then interpolates).

    Method: ADMM on ``W = Z, Z >= 0``, started from per-frame NNLS with a consistent dual. The
    W-step's matrix ``diag(m) (x) G + mu L (x) I + rho I`` (``L`` the path-graph Laplacian with
    Neumann ends) becomes, in the eigenbasis ``V`` of ``G``, ``n_keys`` independent tridiagonal
    systems. When every frame is observed they share ``L``, which the DCT-II diagonalises
    (eigenvalues ``2 - 2 cos(pi q / n)``), so all columns are solved at once by one
    :func:`scipy.fft.dct` / ``idct`` pair and an elementwise division; with unobserved frames the
    ``n_keys`` systems are stacked into one banded system of length ``n_keys * n``, Cholesky-factored
    once per value of rho (:func:`scipy.linalg.cholesky_banded`) and solved with one LAPACK call per
    iteration (no Python loop over columns either way). The Z-step is clipping at zero
    (over-relaxed with 1.6; rho rebalanced from the residuals every 10 iterations when they differ
    tenfold). Stops when the primal residual ``max|W - Z|`` and the dual residual
    ``rho max|Z - Z_prev|`` both fall below ``tol * max(1, max Z)``; ``tol`` bounds these residuals,
    not the distance to the exact solution. Measured on 20,000 frames x 24 keys (lambda 0.1)
    against a ``tol=1e-9`` solution: the default ``tol=1e-5`` (458 iterations) leaves weights within
    6.3e-3 (max) and 6.0e-4 (RMS); on 10,000 frames the objective is within 1e-6 relative and
    ``1e-6`` (936 iterations) within 7e-4. ``tol=1e-10`` matches an exact NNLS of the whole QP
    (scipy's Lawson-Hanson, tests) to 1e-6, and reproduces per-frame NNLS to 1e-7 when
    ``smooth_lambda = 0``. Speed (100,000 frames x 48 points x 24 keys, a shared 2-core machine):
    the iterates equal those of the former per-column loop (to 8e-14) at lower cost per
    iteration: 122.8 s -> 44.8 s back to back in one process (2.7x; ``bench/bench_decompose.py``
    measured 96 s under heavier load). It is still ~459 iterations of 4 passes over the (n, k)
    array, i.e. tens of seconds (see docs/decompose.md), and the per-frame NNLS start costs
    as much as ``nnls_weights``. With ``smooth_lambda = 0`` and every frame observed it
    returns per-frame NNLS (eq. 4) directly. ``ridge`` adds the Tikhonov term of
    :func:`nnls_weights` on observed frames (``G`` becomes ``G + ridge * trace(G) / k * I``).

    Returns
    -------
    (n_frames, n_keys) non-negative weights (and a dict with ``iterations``, ``converged``
    if ``return_info``).
    """
    X, B = _flatten(shapes, keys, neutral)
    n, k = len(X), len(B)
    if smooth_lambda < 0 or not np.isfinite(smooth_lambda):
        raise InputError(f"smooth_lambda must be a non-negative number, got {smooth_lambda}")
    m = np.ones(n) if observed is None else np.asarray(observed, dtype=np.float64)
    if m.shape != (n,):
        raise InputError(f"observed: expected shape ({n},), got {m.shape}")
    G = _gram(B)
    scale = float(np.trace(G)) / k
    if scale <= 0:
        raise InputError("key shapes are all equal to the neutral shape: nothing to decompose onto")
    Gs = _ridged(G, ridge) / scale
    H = (X @ B.T) / scale * m[:, None]          # (n, k) linear term
    mu = float(smooth_lambda)
    s, V = np.linalg.eigh(Gs)
    s = np.maximum(s, 0.0)
    rho = float(np.sqrt(max(s.min(), 1e-6 * s.max()) * s.max())) + mu
    deg = np.full(n, 2.0)
    deg[[0, -1]] = 1.0 if n > 1 else 0.0

    full = bool((m == 1).all())
    if full:
        # every frame observed: the W-step matrix in G's eigenbasis is (s_j + rho) I + mu L, and the
        # DCT-II diagonalises the Neumann path Laplacian L (eigenvalues 2 - 2 cos(pi q / n))
        lam = 2.0 - 2.0 * np.cos(np.pi * np.arange(n) / n)

        def factor(rho):
            return 1.0 / (lam[:, None] * mu + (s + rho)[None, :])

        def wsolve(rhs, fac):
            c = dct(rhs, type=2, norm="ortho", axis=0, overwrite_x=True, workers=_WORKERS)
            c *= fac
            return idct(c, type=2, norm="ortho", axis=0, overwrite_x=True, workers=_WORKERS)
    else:
        def factor(rho):
            # the k tridiagonal systems (diagonal m_t s_j + mu deg_t + rho, off-diagonal -mu), one per
            # eigen-column, stacked into one banded system of length k n (no coupling between blocks)
            ab = np.zeros((2, k, n))
            ab[1] = s[:, None] * m[None, :] + mu * deg[None, :] + rho
            ab[0, :, 1:] = -mu
            return cholesky_banded(ab.reshape(2, k * n), lower=False, check_finite=False)

        def wsolve(rhs, fac):
            x = cho_solve_banded((fac, False), np.ascontiguousarray(rhs.T).ravel(), check_finite=False)
            return x.reshape(k, n).T

    factors = factor(rho)
    # start from per-frame NNLS on the observed frames (exact when mu = 0)
    Z = np.zeros((n, k))
    obs = m > 0
    if obs.any():
        Z[obs] = nnls_gram(Gs, H[obs])[0]
    if mu == 0 and obs.all():
        return (Z, {"iterations": 0, "converged": True}) if return_info else Z
    # dual warm start consistent with Z: U = -grad f(Z) / rho, f the smooth part of the objective
    LZ = np.zeros_like(Z)
    if n > 1:
        dZ = np.diff(Z, axis=0)
        LZ[:-1] -= dZ
        LZ[1:] += dZ
    U = -(Z @ Gs * m[:, None] - H + mu * LZ) / rho
    del LZ
    it, converged = 0, False
    relax = 1.6                                            # over-relaxation (Boyd et al. 2011, 3.4.3)
    T = np.empty_like(Z)
    for it in range(1, max_iter + 1):
        np.subtract(Z, U, out=T)
        T *= rho
        T += H
        W = wsolve(T @ V, factors) @ V.T                   # W-step, solved in G's eigenbasis
        # T <- W_hat + U with W_hat = relax W + (1 - relax) Z; then Z <- max(T, 0), U <- T - Z
        np.multiply(W, relax, out=T)
        T -= (relax - 1.0) * Z
        T += U
        Z_new = np.maximum(T, 0.0)
        np.subtract(T, Z_new, out=U)
        ref = max(1.0, float(Z_new.max()))
        np.subtract(W, Z_new, out=T)
        r_primal = float(np.abs(T).max())
        np.subtract(Z_new, Z, out=T)
        r_dual = rho * float(np.abs(T).max())
        Z = Z_new
        if r_primal < tol * ref and r_dual < tol * ref:
            converged = True
            break
        if it % 10 == 0 and (r_primal > 10 * r_dual or r_dual > 10 * r_primal):
            # residual balancing (Boyd et al. 2011, 3.4.1): rescale rho and the scaled dual U
            f = 2.0 if r_primal > r_dual else 0.5
            rho *= f
            U /= f
            factors = factor(rho)
    return (Z, {"iterations": it, "converged": converged}) if return_info else Z


SOLVERS = ("nnls", "lstsq", "smooth")


def solve_weights(shapes: np.ndarray, keys: np.ndarray, neutral: np.ndarray | None = None,
                  solver: str = "nnls", smooth_lambda: float = 0.1,
                  observed: np.ndarray | None = None, ridge: float = 0.0) -> np.ndarray:
    """Weights of every frame by ``solver`` (``nnls``, ``lstsq`` or ``smooth``).

    ``ridge`` (default 0, the paper's solvers) adds a Tikhonov term on the weights: see
    :func:`nnls_weights`.

    ``observed`` (n_frames,) bool marks frames whose shapes are valid; the others'
    shapes are ignored (they may be NaN). ``smooth`` fills them through its penalty;
    ``nnls`` and ``lstsq`` interpolate each weight linearly in time between the
    nearest observed frames (constant beyond the ends).
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    n = len(shapes)
    obs = np.ones(n, dtype=bool) if observed is None else np.asarray(observed, dtype=bool)
    if obs.shape != (n,):
        raise InputError(f"observed: expected shape ({n},), got {obs.shape}")
    if not obs.any():
        raise InputError("no observed (successful) frames to decompose")
    if solver == "smooth":
        filled = np.where(obs[:, None, None], shapes, 0.0 if neutral is None else neutral)
        return smooth_weights(filled, keys, neutral, smooth_lambda=smooth_lambda, observed=obs, ridge=ridge)
    if solver == "nnls":
        w_obs = nnls_weights(shapes[obs], keys, neutral, ridge=ridge)
    elif solver == "lstsq":
        w_obs = lstsq_weights(shapes[obs], keys, neutral, ridge=ridge)
    else:
        raise InputError(f"unknown solver {solver!r}: use one of {', '.join(SOLVERS)}")
    return interpolate_rows(w_obs, obs)


def interpolate_rows(values: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Spread ``values`` (n_observed, k) over all frames, linearly interpolating unobserved rows."""
    obs = np.asarray(observed, dtype=bool)
    t = np.arange(len(obs))
    out = np.empty((len(obs), values.shape[1]))
    out[obs] = values
    if (~obs).any():
        to = t[obs]
        # one vectorised interpolation: positions of unobserved frames between observed ones
        j = np.clip(np.searchsorted(to, t[~obs]), 1, max(len(to) - 1, 1))
        if len(to) == 1:
            out[~obs] = values[0]
        else:
            t0, t1 = to[j - 1], to[j]
            a = np.clip((t[~obs] - t0) / (t1 - t0), 0.0, 1.0)[:, None]
            out[~obs] = (1 - a) * values[j - 1] + a * values[j]
    return out
