"""Reconstruction error against the number of key shapes, per selector and region (Figure 6),
and the target-domain distortion of Figures 4 and 5.

Design notes and figures: docs/decompose.md, "Notes on the code", ``decompose/compare.py``.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import solve_triangular

from keyshape.base.errors import InputError
from keyshape.base.formats.tracks import Tracks
from keyshape.base.schemes import Scheme
from keyshape.decompose.regions import available_regions, head_shapes, region_points, stable_pose
from keyshape.decompose.selectors import METHODS, make_selector
from keyshape.decompose.weights import nnls_gram, reconstruct

NESTED = ("spread", "greedy")   # the first j keys of a fit with k are the fit with j


def pixel_errors(shapes: np.ndarray, recon: np.ndarray, pose: np.ndarray) -> tuple[float, float]:
    """Eq. (5) in image pixels squared and the RMS point error (px) of model-frame ``recon``."""
    lin = pose[:, :, :2]
    d = recon - shapes
    # |lin_t d_tp|^2 written out (a 2 x 2 map per frame): elementwise, no einsum
    u = lin[:, 0, 0, None] * d[..., 0] + lin[:, 0, 1, None] * d[..., 1]
    v = lin[:, 1, 0, None] * d[..., 0] + lin[:, 1, 1, None] * d[..., 1]
    e = float((u * u).sum() + (v * v).sum())
    return e, float(np.sqrt(e / (d.shape[0] * d.shape[1])))


def smooth_field(points: np.ndarray, amplitude: float, rng=None, n_waves: int = 4,
                 extent: float | None = None) -> "callable":
    """A random smooth displacement field ``f(p) = p + amplitude * phi(p)`` over the model frame.

    ``phi`` sums ``n_waves`` random sinusoids per axis with wavelengths between 0.5 and 1.5 times
    the extent of ``points``, scaled to unit RMS displacement over ``points``.
    """
    rng = np.random.default_rng(rng)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    ext = extent or float(np.ptp(pts, axis=0).max()) or 1.0
    freq = rng.normal(size=(2, n_waves, 2))
    freq *= (2 * np.pi / (ext * rng.uniform(0.5, 1.5, size=(2, n_waves, 1)))) / np.linalg.norm(freq, axis=-1,
                                                                                                  keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, size=(2, n_waves))
    amp = rng.normal(size=(2, n_waves))

    def phi(p):
        p = np.asarray(p, dtype=np.float64)
        return np.stack([np.sin(p @ freq[a].T + phase[a]) @ amp[a] for a in range(2)], axis=-1)

    norm = float(np.sqrt((phi(pts) ** 2).sum(-1).mean())) or 1.0
    return lambda p: np.asarray(p, dtype=np.float64) + amplitude * phi(p) / norm


def _field_cache(shapes: np.ndarray, amplitude: float, n_fields: int, rng) -> list:
    """``n_fields`` random fields ``f`` (:func:`smooth_field`) with ``f(shapes)``: the target-domain check moves the
    keys, the neutral and the frames by one field (the RMS of ``F(w, f(S)) - f(Q)``)."""
    rng = np.random.default_rng(rng)
    out = []
    for _ in range(n_fields):
        f = smooth_field(shapes.reshape(-1, 2)[::max(1, shapes.size // 2000)], amplitude, rng)
        out.append((f, f(shapes)))
    return out


def _key_fields(shapes: np.ndarray, keys: np.ndarray, neutral: np.ndarray, amplitude: float, n_fields: int,
                rng) -> list:
    """Per field, the keys and the neutral each displaced by its own smooth field: an artist re-drawing each key
    with small independent errors (weights of both signs amplify them; the RMS of ``F(w, S + E) - F(w, S)``)."""
    rng = np.random.default_rng(rng)
    sample = shapes.reshape(-1, 2)[::max(1, shapes.size // 2000)]
    return [np.stack([smooth_field(sample, amplitude, rng)(s) for s in np.concatenate([keys, neutral[None]])])
            for _ in range(n_fields)]


class _Basis:
    """One region's frames against the ``kmax`` keys of a nested selector, factored once.

    The keys for k are the first k rows, so their Gram matrix and projections are the
    leading block of the full ones (NNLS, eq. 4, by :func:`nnls_gram`), and least squares is the leading block of one QR of the key basis.
    """

    def __init__(self, Q: np.ndarray, keys: np.ndarray, neutral: np.ndarray, qr_gram: bool = False):
        self.X = (Q - neutral).reshape(len(Q), -1)
        self.B = (keys - neutral).reshape(len(keys), -1)
        self.H = self.X @ self.B.T
        self.q, self.r = np.linalg.qr(self.B.T)
        # qr_gram: R^T R, the Gram matrix nnls_weights forms (same weights as it, to the last bit)
        self.G = self.r.T @ self.r if qr_gram and len(self.B) <= self.B.shape[1] else self.B @ self.B.T
        self.c = self.X @ self.q

    def nnls(self, k: int) -> np.ndarray:
        return nnls_gram(self.G[:k, :k], self.H[:, :k])[0]

    def lstsq(self, k: int) -> np.ndarray:
        r = self.r[:k, :k]
        if k > self.r.shape[0] or np.abs(np.diagonal(r)).min() <= 1e-10 * max(np.abs(np.diagonal(r)).max(), 1e-300):
            # more keys than coordinates, or dependent keys: minimum-norm least squares
            return np.linalg.lstsq(self.B[:k].T, self.X.T, rcond=None)[0].T
        return solve_triangular(r, self.c[:, :k].T).T


def compare(tracks: Tracks, scheme: Scheme, methods=METHODS, regions=None, kmin: int = 2, kmax: int = 24,
            amplitude: float = 3.0, rng=None, progress=None, workers: int | None = None) -> list[dict]:
    """Rows of :data:`COLUMNS` for every method, region and k in kmin..kmax.

    Weights are NNLS (eq. 4), as in Figure 6. ``hull2`` gives one row at its own k. ``random`` uses a fresh draw
    per k. Failed frames are left out. The nested selectors are fitted once at ``kmax``; each (region, method)
    is a job with its own random stream drawn from ``rng`` in a fixed order, run on ``workers`` processes
    (default one per core, at most 4; 1: here), so the rows do not depend on the number of workers.
    ``progress`` (a :class:`keyshape.base.progress.Progress`, or None) counts rows.
    """
    from threadpoolctl import threadpool_limits

    # many small products and factorisations: BLAS/OpenMP threads only add spinning (CPU time 2x on 2 cores);
    # forked workers start from this setting, and each job sets it again (spawned workers do not inherit it)
    with threadpool_limits(1):
        return _compare(tracks, scheme, methods, regions, kmin, kmax, amplitude, rng, progress, workers)


def _compare(tracks, scheme, methods, regions, kmin, kmax, amplitude, rng, progress, workers) -> list[dict]:
    import os
    from concurrent.futures import ProcessPoolExecutor, as_completed

    rng = np.random.default_rng(rng)
    shapes_all, stab = head_shapes(tracks, scheme)              # as keyshape select does by default
    ok = np.flatnonzero(tracks.success)
    if kmax > len(ok):
        raise InputError(f"--kmax {kmax} is larger than the {len(ok)} successful frames")
    if kmin < 1 or kmin > kmax:
        raise InputError(f"need 1 <= kmin <= kmax, got {kmin}..{kmax}")
    regions = available_regions(scheme) if regions is None else list(regions)
    pose = stable_pose(tracks, stab)[ok]
    # every (region, method) is an independent job with its own random stream, drawn here in a fixed
    # order, so the rows do not depend on how many processes run them
    jobs = []
    for region in regions:
        Q = np.ascontiguousarray(shapes_all[ok][:, region_points(scheme, region)])
        field_seed = int(rng.integers(2**31 - 1))
        for method in methods:
            jobs.append((region, method, Q, field_seed, pose, kmin, kmax, amplitude, int(rng.integers(2**63 - 1))))
    size = [1 if j[1] == "hull2" else kmax - kmin + 1 for j in jobs]      # rows per job
    if progress is not None:
        progress.total = sum(size)
    out = [None] * len(jobs)

    def record(i, rows):
        out[i] = rows
        if progress is not None:
            progress.update(size[i])

    workers = max(1, min(4, os.cpu_count() or 1, len(jobs))) if workers is None else int(workers)
    if workers == 1:
        for i, j in enumerate(jobs):
            record(i, _compare_job(*j))
    else:
        # the jobs are many small batched solves that hold the GIL between calls: processes, not threads
        pool = ProcessPoolExecutor(max_workers=workers)
        try:
            futures = {pool.submit(_compare_job, *j): i for i, j in enumerate(jobs)}
            for f in as_completed(futures):
                record(futures[f], f.result())
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    return [row for rows in out for row in rows]


def _compare_job(region, method, Q, field_seed, pose, kmin, kmax, amplitude, seed) -> list[dict]:
    """Rows of one method on one region, k = kmin..kmax (a process-pool job: plain arguments only)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        return _compare_rows(region, method, Q, field_seed, pose, kmin, kmax, amplitude, np.random.default_rng(seed))


def _compare_rows(region, method, Q, field_seed, pose, kmin, kmax, amplitude, rng) -> list[dict]:
    neutral = Q.mean(axis=0)
    fields = _field_cache(Q, amplitude, 3, field_seed)
    rows = []
    basis = None
    if method in NESTED:
        sel = make_selector(method, kmax, rng=rng).fit(Q)
        fits = [(k, sel.order_[:k], Q[sel.order_[:k]]) for k in range(kmin, kmax + 1)]
        basis = _Basis(Q, Q[sel.order_[:kmax]], neutral)
    elif method == "hull2":
        sel = make_selector(method, 0).fit(Q)
        fits = [(len(sel.indices_), sel.indices_, sel.keys_)]
    else:
        fits = []
        for k in range(kmin, kmax + 1):
            sel = make_selector(method, k, rng=rng).fit(Q)
            fits.append((k, sel.indices_, sel.keys_))
    for k, _, keys in fits:
        if basis is None:
            b = _Basis(Q, keys, neutral, qr_gram=True)   # one factorisation for both solvers
            w, wl = b.nnls(len(keys)), b.lstsq(len(keys))
        else:
            w, wl = basis.nnls(k), basis.lstsq(k)
        e, rms = pixel_errors(Q, reconstruct(w, keys, neutral), pose)
        row = {"method": method, "region": region, "k": int(k), "error": e, "rms_px": rms}
        for name, ww in (("nnls", w), ("lstsq", wl)):
            row[f"target_{name}_px"] = float(np.mean(
                [pixel_errors(fQ, reconstruct(ww, f(keys), f(neutral)), pose)[1] for f, fQ in fields]))
        kf = _key_fields(Q, keys, neutral, amplitude, 3, field_seed)
        for name, ww in (("nnls", w), ("lstsq", wl)):
            rec0 = reconstruct(ww, keys, neutral)
            row[f"keynoise_{name}_px"] = float(np.mean(
                [pixel_errors(rec0, reconstruct(ww, fk[:-1], fk[-1]), pose)[1] for fk in kf]))
        rows.append(row)
    return rows


COLUMNS = ("method", "region", "k", "error", "rms_px", "target_nnls_px", "target_lstsq_px",
           "keynoise_nnls_px", "keynoise_lstsq_px")


def write_errors(path, rows: list[dict]) -> None:
    """errors.csv: one row per (method, region, k) with :data:`COLUMNS`."""
    from keyshape.base.files import atomic_write

    with atomic_write(path) as f:
        f.write(",".join(COLUMNS) + "\n")
        for r in rows:
            f.write(",".join([r["method"], r["region"], str(r["k"])]
                             + [f"{r[c]:.6g}" for c in COLUMNS[3:]]) + "\n")


def plot_errors(path, rows: list[dict]) -> None:
    """errors.png: eq. (5) error against k, one line per selector, one panel per region (Figure 6)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from keyshape.base.files import atomic_path

    regions = list(dict.fromkeys(r["region"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    style = {"spread": ("tab:blue", "-"), "kmeans2": ("tab:green", "--"), "kmeans3": ("m", "--"),
             "hull2": ("tab:red", ""), "random": ("0.5", ":"), "greedy": ("k", "-")}
    fig, axes = plt.subplots(1, len(regions), figsize=(5 * len(regions), 4), squeeze=False)
    for ax, region in zip(axes[0], regions):
        for m in methods:
            rr = sorted((r for r in rows if r["region"] == region and r["method"] == m), key=lambda r: r["k"])
            if not rr:
                continue
            c, ls = style.get(m, (None, "-"))
            ks, es = [r["k"] for r in rr], [r["error"] for r in rr]
            if len(rr) == 1 or not ls:
                ax.plot(ks, es, "o", color=c, label=m)
            else:
                ax.plot(ks, es, ls, color=c, label=m, lw=2 if m in ("spread", "greedy") else 1.3)
        ax.set_yscale("log")
        ax.set_xlabel("number of key shapes k")
        ax.set_ylabel("eq. (5) error, sum of squared px")
        ax.set_title(f"{region}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
