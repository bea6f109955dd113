"""Blend target key shapes with per-frame weights, as one matrix product (section 5 of 004_119ba07521a9af0b.txt).

Two forms of the combination:

* **absolute** (the paper's Eq. (2) with linear F, as in Eq. (3)): ``B_t = sum_i w_ti B_i``.
* **delta**: ``B_t = N + sum_i w_ti (B_i - N)`` with a neutral ``N``.

They differ by ``(1 - sum_i w_ti) N``: they agree exactly when the weights of a
frame sum to one and differ otherwise. NNLS weights (section 4.1) are *not*
constrained to sum to one, so the form must be the one the weights were fitted
in; then targets equal to the source key shapes give back the decomposed frames
exactly. ``keyshape decompose`` fits ``Q_t = N + sum_i w_ti (S_i - N)`` with ``N``
the sequence's mean shape (its KEYS.json ``neutral``): replay its weights in the
**delta** form with the target of that face as the neutral (the artist's rest
face is the usual stand-in). The paper's literal fit ``S_t ~ sum_i w_ti S_i`` (no
neutral) is replayed by the **absolute** form. Delta-form weights replayed in the
absolute form would lose ``(1 - sum_i w_ti) N``: a head shrunk or grown about the
origin by the unspent weight. Weights fitted to deltas from a rest face (ARKit,
Live Link, ICT-FaceKit) are delta form too.

Regions (the paper's eye and mouth regions) are folded into the basis: key shape
``i`` of region ``r`` is scaled per vertex by the region weight ``a_r(v)``
(see :func:`region_weights`), so the blend of all regions is still one product
``W @ basis`` over all frames.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError, NotFittedError

FORMS = ("auto", "absolute", "delta")


def _check_weights(weights: np.ndarray, n_keys: int, what: str = "weights") -> np.ndarray:
    w = np.asarray(weights)
    if w.ndim != 2 or w.shape[1] != n_keys:
        raise InputError(f"{what}: expected shape (n_frames, {n_keys}), got {w.shape}")
    if not np.all(np.isfinite(w)):
        i, j = np.argwhere(~np.isfinite(w))[0]
        raise InputError(f"{what}: frame {i} key {j} is {w[i, j]} (weights must be finite)")
    return w


class BlendBasis:
    """Precomputed linear basis: ``frames = offset_ + weights @ basis_``.

    Parameters
    ----------
    form : {"auto", "absolute", "delta"}
        See the module docstring; "delta" needs a neutral; "auto" (default, as
        :class:`~keyshape.retarget.targets.retargeter.Retargeter`) is "delta" when ``fit`` is given a
        neutral, else "absolute".
    dtype : numpy dtype
        Dtype of the stored basis and of the output (float32 halves memory; the
        product accumulates in that dtype; use float64 for exactness tests).

    Attributes
    ----------
    form_ : "absolute" or "delta", the form used
    offset_ : (n_vertices, dim) array, zero in absolute form, the neutral in delta form
    basis_ : (n_keys [+ 1], n_vertices * dim) array, row i is target i (minus the neutral in
        delta form) scaled per vertex by its region's weight; in delta form a last row holds
        the neutral, driven by a constant weight 1, so the neutral costs no extra pass
    n_keys_ : int
    shape_ : (n_vertices, dim)
    """

    def __init__(self, form: str = "auto", dtype=np.float64):
        self.form = form
        self.dtype = dtype

    def fit(self, targets: np.ndarray, neutral: np.ndarray | None = None,
            key_regions: Sequence[int] | None = None, region_weights: np.ndarray | None = None) -> "BlendBasis":
        """Build the basis.

        Parameters
        ----------
        targets : (n_keys, n_vertices, dim)
        neutral : (n_vertices, dim), required for ``form="delta"``, chooses delta for ``form="auto"``
        key_regions : (n_keys,) int, region index of each key shape (with ``region_weights``)
        region_weights : (n_regions, n_vertices), per-vertex weight of each region, columns sum to one
        """
        if self.form not in FORMS:
            raise InputError(f"form must be one of {FORMS}, got {self.form!r}")
        form = self.form
        if form == "auto":
            form = "delta" if neutral is not None else "absolute"
        b = np.asarray(targets, dtype=np.float64)
        if b.ndim != 3:
            raise InputError(f"targets: expected shape (n_keys, n_vertices, dim), got {b.shape}")
        if not np.all(np.isfinite(b)):
            raise InputError("targets contain non-finite coordinates")
        k, nv, dim = b.shape
        offset = np.zeros((nv, dim))
        if form == "delta":
            if neutral is None:
                raise InputError("the delta form needs a neutral (--neutral)")
            n = np.asarray(neutral, dtype=np.float64)
            if n.shape != (nv, dim):
                raise InputError(f"neutral: expected shape {(nv, dim)}, got {n.shape}")
            b = b - n
            offset = n
        if region_weights is not None:
            rw = np.asarray(region_weights, dtype=np.float64)
            kr = np.asarray(key_regions, dtype=np.intp)
            if rw.ndim != 2 or rw.shape[1] != nv:
                raise InputError(f"region weights: expected shape (n_regions, {nv}), got {rw.shape}")
            if kr.shape != (k,) or kr.min() < 0 or kr.max() >= len(rw):
                raise InputError(f"key_regions: expected {k} indices into {len(rw)} regions")
            b = b * rw[kr][:, :, None]
        self.form_ = form
        self.shape_ = (nv, dim)
        self.n_keys_ = k
        self.offset_ = offset.astype(self.dtype)
        rows = b.reshape(k, nv * dim)
        if form == "delta":
            rows = np.concatenate([rows, offset.reshape(1, -1)])
        self.basis_ = np.ascontiguousarray(rows, dtype=self.dtype)
        return self

    def transform(self, weights: np.ndarray, out: np.ndarray | None = None,
                  chunk_frames: int | None = None) -> np.ndarray:
        """Evaluate all frames: ``(n_frames, n_vertices, dim)``.

        One matrix product ``weights @ basis_`` (BLAS GEMM; in delta form the
        weights get a last column of ones for the neutral row), written into ``out``
        when given; ``chunk_frames`` splits the frames into blocks of that many
        rows to bound the temporary memory (no temporary at all with ``out`` of
        the basis dtype).
        """
        if not hasattr(self, "basis_"):
            raise NotFittedError("BlendBasis is not fitted: call fit(targets, ...) first")
        k = self.n_keys_
        w = _check_weights(weights, k)
        n = len(w)
        if self.form_ == "delta":
            w = np.concatenate([w, np.ones((n, 1))], axis=1)
        w = w.astype(self.dtype, copy=False)
        if out is None:
            out = np.empty((n, *self.shape_), dtype=self.dtype)
        elif out.shape != (n, *self.shape_) or not out.flags.c_contiguous:
            raise InputError(f"out: expected a C-contiguous array of shape {(n, *self.shape_)}, got {out.shape}")
        flat = out.reshape(n, -1)
        step = n if not chunk_frames else max(1, int(chunk_frames))
        for s in range(0, n, step):   # blocks of frames, not frames: one GEMM each
            if flat.dtype == self.dtype:
                np.matmul(w[s:s + step], self.basis_, out=flat[s:s + step])
            else:
                flat[s:s + step] = w[s:s + step] @ self.basis_
        return out

    __call__ = transform


def blend(weights: np.ndarray, targets: np.ndarray, neutral: np.ndarray | None = None,
          form: str = "auto", dtype=np.float64) -> np.ndarray:
    """Blend ``targets`` (n_keys, n_vertices, dim) with ``weights`` (n_frames, n_keys) in one product.

    ``form`` is "absolute", "delta" (needs ``neutral``) or "auto" (default: delta when
    ``neutral`` is given, else absolute, as :class:`~keyshape.retarget.targets.retargeter.Retargeter`);
    see the module docstring.

    Examples
    --------
    >>> import numpy as np
    >>> B = np.stack([np.zeros((2, 3)), np.ones((2, 3))])
    >>> blend(np.array([[0.25, 0.5]]), B)[0, 0]
    array([0.5, 0.5, 0.5])
    >>> blend(np.array([[0.25, 0.5]]), B, neutral=np.ones((2, 3)))[0, 0]       # delta: 1 + 0.25 * -1
    array([0.75, 0.75, 0.75])
    """
    return BlendBasis(form, dtype).fit(targets, neutral).transform(weights)


def region_weights(vertices: np.ndarray, groups: Sequence[np.ndarray], band: float,
                   edges: np.ndarray | None = None, metric: str = "euclidean") -> np.ndarray:
    """Per-vertex weights of each region, falling off linearly across a band.

    For vertex ``v`` with distance ``d_r(v)`` to region ``r``'s vertex group and
    ``d_min(v) = min_r d_r(v)``, the raw weight is
    ``a_r(v) = clip(1 - (d_r(v) - d_min(v)) / band, 0, 1)`` and the region weight is
    ``a_r / sum_s a_s``. So a vertex nearer to one region than to every other by
    more than ``band`` belongs to it alone; on the midline between two regions each
    gets 1/2; every vertex gets weights summing to one (vertices far from every
    group follow the nearest region). The weights are continuous (Lipschitz, slope
    at most ``2 / band`` per unit of distance), so the blended mesh has no step at the band.

    Parameters
    ----------
    vertices : (n_vertices, dim)
    groups : n_regions arrays of vertex indices (the regions' vertex groups)
    band : width of the band, in mesh units (> 0)
    edges : (n_edges, 2) vertex index pairs, required for ``metric="geodesic"``
    metric : "euclidean" (straight-line distance) or "geodesic" (shortest path along mesh edges,
        scipy.sparse.csgraph.dijkstra). Vertices on shells that no group reaches along edges (teeth,
        eyeballs: separate shells) use the Euclidean distances instead, so lower teeth follow the mouth.

    Returns
    -------
    (n_regions, n_vertices) float64, columns summing to one
    """
    v = np.asarray(vertices, dtype=np.float64)
    if not band > 0:
        raise InputError(f"band must be > 0, got {band}")
    if len(groups) == 0:
        raise InputError("no regions given")
    d = np.empty((len(groups), len(v)))
    for r, g in enumerate(groups):    # a handful of regions, each vectorised
        g = np.asarray(g, dtype=np.intp)
        if g.size == 0 or g.min() < 0 or g.max() >= len(v):
            raise InputError(f"region {r}: vertex indices must be non-empty and within 0..{len(v) - 1}")
        if metric == "euclidean":
            from scipy.spatial import cKDTree
            d[r] = cKDTree(v[g]).query(v)[0]
        elif metric == "geodesic":
            if edges is None:
                raise InputError("geodesic distance needs the mesh edges")
            from scipy.sparse import coo_matrix
            from scipy.sparse.csgraph import dijkstra
            e = np.asarray(edges, dtype=np.intp)
            length = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
            graph = coo_matrix((length, (e[:, 0], e[:, 1])), shape=(len(v), len(v))).tocsr()
            d[r] = dijkstra(graph, directed=False, indices=g, min_only=True)
        else:
            raise InputError(f"metric must be 'euclidean' or 'geodesic', got {metric!r}")
    unreached = ~np.isfinite(d).any(axis=0)
    if unreached.any():
        from scipy.spatial import cKDTree
        for r, g in enumerate(groups):
            d[r, unreached] = cKDTree(v[np.asarray(g, dtype=np.intp)]).query(v[unreached])[0]
    dmin = d.min(axis=0)
    with np.errstate(invalid="ignore"):
        a = np.clip(1.0 - (d - dmin) / band, 0.0, 1.0)
    a[~np.isfinite(a)] = 0.0      # a group this vertex's shell does not reach
    return a / a.sum(axis=0)


def mesh_edges(polygons: Sequence[np.ndarray]) -> np.ndarray:
    """Unique undirected edges ``(n_edges, 2)`` of polygons (each polygon's boundary)."""
    if not len(polygons):
        return np.zeros((0, 2), np.intp)
    sizes = np.array([len(p) for p in polygons])
    flat = np.concatenate(polygons).astype(np.intp)
    starts = np.repeat(np.cumsum(sizes) - sizes, sizes)
    pos = np.arange(len(flat)) - starts
    nxt = flat[starts + (pos + 1) % np.repeat(sizes, sizes)]
    e = np.sort(np.stack([flat, nxt], axis=1), axis=1)
    return np.unique(e, axis=0)
