"""Blend weights of key shapes for every frame: least squares, NNLS (eq. 4) and smoothed NNLS.

Design notes and figures: docs/decompose.md, "Notes on the code", ``decompose/weights.py``.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import os

from scipy.fft import dct, idct
from scipy.linalg import cho_solve_banded, cholesky_banded

from keyshape.base.errors import InputError
from keyshape.decompose.defaults import SOLVERS

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
    shape = (len(w),) + keys.shape[1:]
    if neutral is None:
        return (w @ keys.reshape(len(keys), -1)).reshape(shape)
    neutral = np.asarray(neutral, dtype=np.float64)
    out = (w @ (keys - neutral).reshape(len(keys), -1)).reshape(shape)   # one BLAS product, not einsum
    out += neutral
    return out


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

_CHUNK = 512  # frames per vectorised Cholesky block: keeps the (p, p, chunk) block in cache


def _chol_solve_stacked(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``A[:, :, i] x_i = b[:, i]`` for a stack of small SPD matrices, in place.

    ``A`` (p, p, n) and ``b`` (p, n), the stack on the last (contiguous) axis, so each
    step of the Cholesky factorisation ``A = R^T R`` and of the two triangular solves is
    one vectorised operation over all n systems (no per-matrix LAPACK call). Pivots are
    floored at 1e-300: callers add a tiny ridge, so only exactly singular input hits it.
    """
    p = A.shape[0]
    for j in range(p):
        d = np.sqrt(np.maximum(A[j, j], 1e-300))
        A[j, j:] /= d
        b[j] /= d
        if j + 1 < p:
            r = A[j, j + 1:]
            A[j + 1:, j + 1:] -= r[:, None] * r[None, :]
            b[j + 1:] -= r * b[j]
    for j in range(p - 1, -1, -1):
        if j + 1 < p:
            b[j] -= np.einsum("in,in->n", A[j, j + 1:], b[j + 1:])
        b[j] /= A[j, j]
    return b


def _passive_solve(G: np.ndarray, h: np.ndarray, passive: np.ndarray) -> np.ndarray:
    """Solve ``G_PP w_P = h_P`` for every row's passive set P (w = 0 elsewhere), batched.

    ``G`` (k, k) shared or (m, k, k), ``h`` (m, k), ``passive`` (m, k) bool. Rows are grouped
    by ``p = |P|``; each group's compact (p, p) systems are gathered with one ``take`` and
    solved by :func:`_chol_solve_stacked` in blocks of :data:`_CHUNK` rows.
    """
    m, k = h.shape
    x = np.zeros((m, k))
    Gf = np.ascontiguousarray(G).reshape(-1)
    batched = G.ndim == 3
    cnt = passive.sum(axis=1)
    for p in np.unique(cnt):
        if p == 0:
            continue
        rows = np.flatnonzero(cnt == p)
        idx = np.nonzero(passive[rows])[1].reshape(len(rows), p)
        for c0 in range(0, len(rows), _CHUNK):
            r = rows[c0:c0 + _CHUNK]
            ii = idx[c0:c0 + _CHUNK].T                         # (p, n)
            flat = ii[:, None, :] * k + ii[None, :, :]
            if batched:
                flat = flat + (r * (k * k))[None, None, :]
            A = np.take(Gf, flat)
            b = np.ascontiguousarray(np.take_along_axis(h[r], ii.T, axis=1).T)
            x[r[:, None], ii.T] = _chol_solve_stacked(A, b).T
    return x


_COVER = 0.5  # smoothed NNLS: re-solve only the frames near infeasible weights while they cover less
_TAIL = 64  # rows left to pivot below which each is finished by scipy's Lawson-Hanson instead


def _lawson_hanson_rows(Gs: np.ndarray, hs: np.ndarray, w: np.ndarray, converged: np.ndarray,
                        rows: np.ndarray) -> None:
    """Finish a few rows exactly with :func:`scipy.optimize.nnls` (Lawson-Hanson) on the k-sized
    problem ``min ||R v - R^-T h||`` with ``G = R^T R``: the long tail of the pivoting costs a few
    Python-level iterations per row otherwise."""
    from scipy.linalg import cholesky, solve_triangular
    from scipy.optimize import nnls

    k = hs.shape[1]
    R = None if Gs.ndim == 3 else cholesky(Gs)
    for r in rows:
        Rr = cholesky(Gs[r]) if R is None else R
        v, _ = nnls(Rr, solve_triangular(Rr, hs[r], trans="T"), maxiter=50 * k)
        w[r] = v
        converged[r] = True


def _bpp(Gs: np.ndarray, hs: np.ndarray, passive: np.ndarray, htol: float, max_iter: int,
         w: np.ndarray, converged: np.ndarray, todo: np.ndarray) -> None:
    """Block principal pivoting (Kim and Park 2011) on rows ``todo``; fills ``w`` and ``converged``."""
    k = hs.shape[1]
    batched = Gs.ndim == 3
    n_bad_best = np.full(len(hs), k + 1)
    backup = np.full(len(hs), 3)
    for _ in range(max_iter):
        if len(todo) <= _TAIL:
            _lawson_hanson_rows(Gs, hs, w, converged, todo)
            return
        P = passive[todo]
        Gt = Gs[todo] if batched else Gs
        x = _passive_solve(Gt, hs[todo], P)
        y = (np.einsum("mij,mj->mi", Gt, x) if batched else x @ Gs) - hs[todo]
        infeasible = (P & (x < -htol)) | (~P & (y < -1e-3 * htol))
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
        x = _passive_solve(Gs[todo] if batched else Gs, hs[todo], passive[todo])
        w[todo] = np.maximum(x, 0.0) * passive[todo]


def nnls_gram(G: np.ndarray, h: np.ndarray, max_iter: int | None = None, tol: float = 1e-10,
              passive: np.ndarray | None = None, coarse: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Exact NNLS ``min_{w >= 0} w^T G w - 2 h^T w`` for many right-hand sides at once.

    Block principal pivoting (Kim and Park 2011), ending at the KKT point Lawson-Hanson finds (eq. 4), with a
    warm start over rows in time order; the method: docs/decompose.md, "Notes on the code".

    Parameters
    ----------
    G : (n_keys, n_keys) or (m, n_keys, n_keys)
        Positive definite Gram matrix ``B B^T`` (one shared, or one per problem).
    h : (m, n_keys)
        Projections ``X B^T``.
    max_iter : int, optional
        Pivoting iterations (default ``10 * n_keys``) per stage.
    tol : float
        Relative feasibility tolerance of the weights (``w_P > -tol``, then clipped at 0); the
        gradient of the zero weights must satisfy the tighter ``y > -tol / 1000``.
    passive : (m, n_keys) bool, optional
        Initial guess of the positive weights (warm start); default: those
        positive in the unconstrained solution (with the hierarchical warm start for a shared ``G``).
    coarse : int
        Stride of the first stage of the warm start (a power of two; 1 = off).

    Returns
    -------
    w : (m, n_keys) non-negative weights.
    converged : (m,) bool.
    """
    G = np.asarray(G, dtype=np.float64)
    h = np.atleast_2d(np.asarray(h, dtype=np.float64))
    k = h.shape[1]
    max_iter = 10 * k if max_iter is None else max_iter
    # Jacobi scaling: solve for v = D^-1 w with D = diag(G)^-1/2 (unit-diagonal Gram, same signs), so
    # the ridge below is small against every key, however different their sizes; zero keys get w = 0
    diag = np.diagonal(G, axis1=-2, axis2=-1)
    dsc = np.where(diag > 0, 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0)), 0.0)
    Gs = G * dsc[..., :, None] * dsc[..., None, :] + np.eye(k) * 1e-13  # ridge guards exactly collinear keys
    hs = h * dsc
    htol = tol * max(1.0, float(np.abs(hs).max(initial=0.0)))
    w, converged = _nnls_scaled(Gs, hs, htol, max_iter, passive, coarse)
    return w * dsc, converged


def _nnls_scaled(Gs, hs, htol, max_iter, passive, coarse):
    """:func:`nnls_gram` on the unit-diagonal problem."""
    m, k = hs.shape
    batched = Gs.ndim == 3
    w = np.zeros((m, k))
    converged = np.zeros(m, dtype=bool)
    if passive is not None or batched or coarse <= 1 or m < 512:
        if passive is None:
            passive = (np.linalg.solve(Gs, hs[..., None])[..., 0] > 0 if batched
                       else np.linalg.solve(Gs, hs.T).T > 0)
        passive = np.array(passive, dtype=bool)
        _bpp(Gs, hs, passive, htol, max_iter, w, converged, np.arange(m))
        return w, converged
    stride = 1 << int(np.log2(min(coarse, m // 256)))     # the first stage keeps >= 256 rows
    rows = np.arange(0, m, stride)
    passive = np.zeros((m, k), dtype=bool)
    passive[rows] = np.linalg.solve(Gs, hs[rows].T).T > 0
    _bpp(Gs, hs, passive, htol, max_iter, w, converged, rows)
    while stride > 1:
        stride //= 2
        rows = np.arange(stride, m, 2 * stride)
        passive[rows] = w[rows - stride] > 0
        _bpp(Gs, hs, passive, htol, max_iter, w, converged, rows)
    return w, converged


def _ridged(G: np.ndarray, ridge: float) -> np.ndarray:
    """``G + ridge * (trace(G) / k) * I``: the Tikhonov term ``ridge * s * ||w||^2`` with ``s`` the
    mean key shape's squared size, so ``ridge`` is dimensionless (0 = the paper's eq. 4)."""
    if not (np.isfinite(ridge) and ridge >= 0):
        raise InputError(f"ridge must be a non-negative number, got {ridge}")
    if ridge == 0:
        return G
    return G + ridge * float(np.trace(G)) / len(G) * np.eye(len(G))


class SolveResult(NamedTuple):
    """What every weight solver's ``*_result`` function returns (one type whatever the solver).

    Attributes
    ----------
    weights : (n_frames, n_keys) float64, never negative
    converged : (n_frames,) bool: per frame for NNLS (the active-set iterations ended); for the
        smoothed QP, one flag for the whole sequence repeated per frame
    iterations : iterations of the method (0 where the solution is direct)
    method : the method that produced ``weights`` (``nnls``; ``pdas``, ``admm`` or ``pdas, then admm``)
    """

    weights: np.ndarray
    converged: np.ndarray
    iterations: int
    method: str


def nnls_weights(shapes: np.ndarray, keys: np.ndarray, neutral: np.ndarray | None = None,
                 ridge: float = 0.0) -> np.ndarray:
    """Non-negative least-squares weights, eq. (4): :func:`nnls_result`'s ``weights``."""
    return nnls_result(shapes, keys, neutral, ridge).weights


def nnls_result(shapes: np.ndarray, keys: np.ndarray, neutral: np.ndarray | None = None,
                ridge: float = 0.0) -> SolveResult:
    """Non-negative least-squares weights, eq. (4) of 004_119ba07521a9af0b.txt, for all frames at once.

    ``min_{w_t >= 0} ||Q_t - neutral - sum_i w_ti (S_i - neutral)||^2`` for each frame ``t`` (:func:`nnls_gram`
    on the key basis' Gram matrix; the result equals ``scipy.optimize.nnls`` frame by frame).

    Parameters
    ----------
    shapes : (n_frames, n_points, dim)
    keys : (n_keys, n_points, dim)
    neutral : (n_points, dim) or None
    ridge : float
        Optional Tikhonov term ``ridge * (trace(G) / n_keys) * ||w_t||^2`` added to eq. (4) (0, the default,
        is the paper's NNLS): it keeps tracking noise off keys whose 2D deltas are small.

    Returns
    -------
    :class:`SolveResult`: (n_frames, n_keys) weights, never negative, and the per-frame convergence flags.
    """
    X, B = _flatten(shapes, keys, neutral)
    G = _ridged(_gram(B), ridge)
    w, ok = nnls_gram(G, X @ B.T)
    return SolveResult(w, np.asarray(ok, dtype=bool), 0, "nnls")


# --------------------------------------------------------------------------- smoothed NNLS

def smooth_weights(shapes: np.ndarray, keys: np.ndarray, neutral: np.ndarray | None = None,
                   smooth_lambda: float = 0.1, observed: np.ndarray | None = None,
                   max_iter: int = 3000, tol: float = 1e-5, ridge: float = 0.0,
                   anderson: int = 10, method: str = "pdas") -> np.ndarray:
    """NNLS with a penalty on frame-to-frame weight change: :func:`smooth_result`'s ``weights``."""
    return smooth_result(shapes, keys, neutral, smooth_lambda, observed, max_iter, tol, ridge, anderson,
                         method).weights


def smooth_result(shapes: np.ndarray, keys: np.ndarray, neutral: np.ndarray | None = None,
                  smooth_lambda: float = 0.1, observed: np.ndarray | None = None,
                  max_iter: int = 3000, tol: float = 1e-5, ridge: float = 0.0,
                  anderson: int = 10, method: str = "pdas") -> SolveResult:
    """NNLS over the whole sequence with a penalty on frame-to-frame weight change, as one QP.

    Solves ``min_{W >= 0} sum_t m_t ||B^T w_t - x_t||^2 + mu sum_t ||w_t - w_{t-1}||^2`` with
    ``mu = smooth_lambda * trace(G) / n_keys``, ``m_t`` = 1 for observed frames and 0 for failed ones (whose
    weights the penalty interpolates), by ``method`` ``pdas`` (:func:`_smooth_pdas`, at most 200 iterations) or
    ``admm`` (:func:`_smooth_admm` with Anderson memory ``anderson``, to ``tol``; also PDAS's fallback); the
    methods: docs/decompose.md, "Notes on the code". ``ridge`` adds :func:`nnls_weights`' Tikhonov term.

    Returns
    -------
    :class:`SolveResult`: (n_frames, n_keys) non-negative weights, whether the method converged
    (one flag, per frame), its iterations and the method used.
    """
    X, B = _flatten(shapes, keys, neutral)
    n, k = len(X), len(B)
    if method not in ("pdas", "admm"):
        raise InputError(f"unknown smooth method {method!r}: use pdas or admm")
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
    # start from per-frame NNLS on the observed frames (exact when mu = 0)
    Z = np.zeros((n, k))
    obs = m > 0
    if obs.any() and (mu == 0 or method == "admm" or not obs.all()):
        Z[obs] = nnls_gram(Gs, H[obs])[0]
    if mu == 0:
        # per-frame NNLS (eq. 4); unobserved frames have no data and no penalty: weights 0
        return SolveResult(Z, np.ones(n, dtype=bool), 0, method)
    if method == "pdas":
        W0 = Z
        if obs.all():
            # warm start nearer the smoothed solution: per-frame NNLS fit of the unconstrained smoothed
            # weights (one DCT solve, see _smooth_admm) instead of the data; saves ~2 PDAS iterations
            s_, V = np.linalg.eigh(Gs)
            lam = 2.0 - 2.0 * np.cos(np.pi * np.arange(n) / n)
            c = dct(H @ V, type=2, norm="ortho", axis=0, workers=_WORKERS)
            c /= lam[:, None] * mu + np.maximum(s_, 1e-12 * s_.max())[None, :]
            u = idct(c, type=2, norm="ortho", axis=0, workers=_WORKERS) @ V.T
            W0 = nnls_gram(Gs, u @ Gs)[0]
        W, it, converged = _smooth_pdas(Gs, H, m, mu, W0.copy(), min(max_iter, 200), tol=tol)
        if not converged:                       # safety net: ADMM from the per-frame start
            if not Z.any() and obs.any():
                Z[obs] = nnls_gram(Gs, H[obs])[0]
            W, it2, converged = _smooth_admm(Gs, H, m, mu, Z, max_iter, tol, anderson)
            it += it2
            method = "pdas, then admm"
    else:
        W, it, converged = _smooth_admm(Gs, H, m, mu, Z, max_iter, tol, anderson)
    return SolveResult(W, np.full(n, bool(converged)), int(it), method)


def _smooth_pdas(Gs: np.ndarray, H: np.ndarray, m: np.ndarray, mu: float, W: np.ndarray, max_iter: int,
                 window: int = 32, tol: float = 1e-10):
    """Exact active-set solution of the smoothed-NNLS QP (primal-dual active set, Hintermueller,
    Ito and Kunisch 2002), started from ``W`` (per-frame NNLS); see :func:`smooth_weights`.

    Frames within ``window`` of the infeasible weights are re-solved while those cover under :data:`_COVER` of the
    take (the method: docs/decompose.md). Returns ``(W, iterations, converged)``; ``converged`` is False on a
    failed factorisation or after ``max_iter``.
    """
    from scipy.linalg.lapack import dpbtrf, dpbtrs
    from threadpoolctl import threadpool_limits

    n, k = H.shape
    deg = np.full(n, 2.0)
    deg[[0, -1]] = 1.0 if n > 1 else 0.0
    dg = np.diagonal(Gs).copy()
    eps = 1e-12 * max(1.0, float(dg.max()))     # guards a singular Gram matrix (dependent keys)
    penalty = 1e12 * max(1.0, float(dg.max()) + 2.0 * mu)
    # one frame's columns of the band (upper storage, column j = (t, b) holds rows k - d for
    # Q[(t, b - d), (t, b)] and row 0 for the link -mu to (t - 1, b)); frames are filled from it
    tpl = np.zeros((k, k + 1))
    for d in range(k):
        tpl[d:, k - d] = np.diagonal(Gs, d)
    tpl[:, 0] = -mu
    htol = min(tol, 1e-10) * max(1.0, float(np.abs(H).max(initial=0.0)))   # sign decisions
    ktol = max(tol, 1e-10) * max(1.0, float(np.abs(H).max(initial=0.0)))   # stationarity of free weights
    unobserved = m == 0
    buf = np.empty((n, k, k + 1))              # LAPACK band storage in Fortran order, reused

    def qmul(W):
        out = (W @ Gs) * m[:, None]
        if n > 1:
            d = np.diff(W, axis=0)
            d *= mu
            out[:-1] -= d
            out[1:] += d
        return out

    def solve(idx, act):
        """New weights of frames ``idx`` (sorted) with the others fixed; active ones at zero."""
        ns = len(idx)
        at = slice(None) if ns == n else idx   # all frames: views, no gathers
        ab = buf[:ns]
        ab[...] = tpl
        if unobserved.any():
            ab[unobserved[at], :, 1:] = 0.0
        ab[:, :, k] += (mu * deg[at] + eps)[:, None] + penalty * act[at]
        link = np.zeros(ns, dtype=bool)
        link[1:] = np.diff(idx) == 1
        ab[~link, :, 0] = 0.0
        rhs = H[idx]                           # a copy (fancy indexing)
        if ns < n:
            before = (idx > 0) & ~link         # a fixed frame just before: its weights enter the rhs
            rhs[before] += mu * W[idx[before] - 1]
            nlink = np.zeros(ns, dtype=bool)
            nlink[:-1] = link[1:]
            after = (idx < n - 1) & ~nlink
            rhs[after] += mu * W[idx[after] + 1]
        actf = act[at]
        rhs[actf] = 0.0
        c, info = dpbtrf(ab.reshape(ns * k, k + 1).T, lower=0, overwrite_ab=1)
        if info != 0:
            return None
        x, info = dpbtrs(c, rhs.reshape(-1, 1), lower=0, overwrite_b=1)
        x = x.reshape(ns, k)
        x[actf] = 0.0
        return x

    def iterate(W):
        everything = np.arange(n)
        g = qmul(W) - H
        act = (W <= 0) & (g > 0)
        idx = everything
        best, stall, sweeps, windows = np.inf, 0, 0, True
        kernel = np.ones(2 * window + 1)
        for it in range(1, max_iter + 1):
            x = solve(idx, act)
            if x is None:
                return W, it, False
            W[idx if len(idx) < n else slice(None)] = x
            g = qmul(W) - H
            bad = (act & (g < -htol)) | (~act & (W < -htol))
            # free weights off their equations: next to frames that a windowed solve held fixed
            off = ~act & (np.abs(g) > ktol)
            n_bad = int(bad.sum())
            if n_bad == 0 and not off.any():
                return np.maximum(W, 0.0), it, True
            if n_bad == 0:
                sweeps += 1
            else:
                sweeps = 0
                if n_bad < best:
                    best, stall = n_bad, 0
                else:
                    stall += 1
            if stall < 3:
                act ^= bad                           # exchange every infeasible weight
            else:
                # the count stopped falling (PDAS can cycle when Q is not an M-matrix): as block
                # principal pivoting does, exchange only the last infeasible weight (Murty's rule,
                # finite), over all frames from now on, until the count falls below its best
                windows = False
                act.ravel()[np.flatnonzero(bad.ravel())[-1]] ^= True
            near = np.convolve((bad | off).any(axis=1), kernel, mode="same") > 0.5
            idx = np.flatnonzero(near) if windows and near.sum() < _COVER * n and sweeps < 3 else everything
        return np.maximum(W, 0.0), max_iter, False

    with threadpool_limits(1):   # OpenBLAS threads make dpbtrf's many tiny level-2 calls ~35x slower
        return iterate(W)


def _smooth_admm(Gs: np.ndarray, H: np.ndarray, m: np.ndarray, mu: float, Z0: np.ndarray, max_iter: int,
                 tol: float, anderson: int):
    """The smoothed-NNLS QP by ADMM (the solver before the active-set method; ``method="admm"``):
    see :func:`smooth_weights`. Returns ``(W, iterations, converged)``."""
    n, k = H.shape
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
    Z = Z0.copy()
    # dual warm start consistent with Z: U = -grad f(Z) / rho, f the smooth part of the objective
    LZ = np.zeros_like(Z)
    if n > 1:
        dZ = np.diff(Z, axis=0)
        LZ[:-1] -= dZ
        LZ[1:] += dZ
    U = -(Z @ Gs * m[:, None] - H + mu * LZ) / rho
    del LZ
    it, converged = 0, False
    relax = 1.0 if anderson else 1.6                       # over-relaxation (Boyd et al. 2011, 3.4.3)
    acc = _Anderson(anderson, Z.size)
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
        ref = max(1.0, float(Z_new.max()))
        r_primal = float(np.abs(W - Z_new).max())
        r_dual = rho * float(np.abs(Z_new - Z).max())
        if r_primal < tol * ref and r_dual < tol * ref:
            Z = Z_new
            converged = True
            break
        # the state after a Z-step is S = Z + U (Z = max(S, 0), U = min(S, 0)); ADMM is the map S -> T,
        # which Anderson acceleration extrapolates (the first step's start is not such a state)
        S = acc.step(Z + U, T) if it > 1 else T
        Z = np.maximum(S, 0.0)
        U = np.minimum(S, 0.0)
        if it % 10 == 0 and (r_primal > 10 * r_dual or r_dual > 10 * r_primal):
            # residual balancing (Boyd et al. 2011, 3.4.1): rescale rho and the scaled dual U
            f = 2.0 if r_primal > r_dual else 0.5
            rho *= f
            U /= f
            factors = factor(rho)
            acc.reset()                                    # a new map: forget the old differences
    return Z, it, converged


class _Anderson:
    """Type-II Anderson acceleration of a fixed-point map ``S -> T(S)`` (Walker and Ni 2011).

    Keeps the last ``mem`` differences of residuals ``F = T(S) - S`` and of map values in
    ring buffers (``mem`` x size) and returns ``T(S) - dG gamma`` with ``gamma`` the
    least-squares fit of ``F`` by ``dF``; one matrix-vector product per buffer per step.
    Safeguard: when the residual norm grows 10x over the best seen, the memory is cleared
    and the plain step is taken.
    """

    def __init__(self, mem: int, size: int):
        self.mem = int(mem)
        self.dF = np.empty((self.mem, size)) if self.mem else None
        self.dG = np.empty((self.mem, size)) if self.mem else None
        self.reset()

    def reset(self) -> None:
        self.n = 0
        self.pos = 0
        self.M = np.zeros((self.mem, self.mem))
        self.f = self.g = None
        self.best = np.inf

    def step(self, s: np.ndarray, g: np.ndarray) -> np.ndarray:
        if not self.mem:
            return g
        f = (g - s).ravel()
        g = g.ravel()
        fn = float(f @ f)
        if fn > 100.0 * self.best:                          # diverging: restart from the plain step
            self.reset()
        self.best = min(self.best, fn)
        if self.f is not None:
            i = self.pos
            np.subtract(f, self.f, out=self.dF[i])
            np.subtract(g, self.g, out=self.dG[i])
            self.n = min(self.n + 1, self.mem)
            self.pos = (i + 1) % self.mem
            col = self.dF[:self.n] @ self.dF[i]
            self.M[i, :self.n] = col
            self.M[:self.n, i] = col
        self.f, self.g = f.copy(), g.copy()
        if not self.n:
            return g.reshape(s.shape)
        M = self.M[:self.n, :self.n]
        rhs = self.dF[:self.n] @ f
        gamma = np.linalg.lstsq(M + 1e-12 * np.trace(M) * np.eye(self.n), rhs, rcond=None)[0]
        return (g - gamma @ self.dG[:self.n]).reshape(s.shape)


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
