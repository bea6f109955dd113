"""Geometry shared by every stage: 2D affine maps, rigid and similarity fits, Procrustes means.

Coordinates are ``(x, y)`` (or ``(x, y, z)``) float arrays of shape ``(n_points, d)``;
in images, pixels with OpenCV's pixel-centre convention. An affine transform is a
``(2, 3)`` array named by the frames it maps between: ``image_from_model`` sends model
coordinates to image coordinates, ``[x', y'] = A[:, :2] @ [x, y] + A[:, 2]``.

Rigid motions (any dimension) are ``x_frame = x_ref @ R.T + t`` (``R`` a proper rotation,
column-vector convention), ``frame_from_ref``: :func:`rigid_fit` solves the weighted
least-squares (Kabsch/Umeyama) problem for every frame at once with one batched SVD; a
point hidden in a frame (NaN) simply has weight 0 there. :func:`robust_rigid_fit` adds
outlier rejection (scikit-image's RANSAC) in the frames where that fit leaves a large residual.
"""
from __future__ import annotations

import warnings

import numpy as np

from keyshape.base.errors import InputError


def _ransac_euclidean3d():
    """scikit-image's ``ransac`` and a 3D ``EuclideanTransform`` class for it, imported when first needed
    (scikit-image and the SciPy it loads take about a second to import; ``keyshape track`` never needs them)."""
    from skimage.measure import ransac
    from skimage.transform import EuclideanTransform

    if hasattr(EuclideanTransform, "from_estimate"):     # scikit-image >= 0.26: dimension from the data
        return ransac, EuclideanTransform

    class _Euclidean3D(EuclideanTransform):              # older: ``ransac`` builds ``model_class()`` itself
        def __init__(self):
            super().__init__(dimensionality=3)

    return ransac, _Euclidean3D


def apply_affine(affine: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map ``points`` (..., 2) by the ``(2, 3)`` ``affine``."""
    a = np.asarray(affine, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ a[:, :2].T + a[:, 2]


def invert_affine(affine: np.ndarray) -> np.ndarray:
    """Inverse of a ``(2, 3)`` affine (``model_from_image`` from ``image_from_model``)."""
    a = np.asarray(affine, dtype=np.float64)
    m = np.linalg.inv(a[:, :2])
    return np.hstack([m, -(m @ a[:, 2])[:, None]])


def compose_affine(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """``outer ∘ inner``: first ``inner`` then ``outer`` (``c_from_a = compose(c_from_b, b_from_a)``)."""
    o, i = np.asarray(outer, np.float64), np.asarray(inner, np.float64)
    return np.hstack([o[:, :2] @ i[:, :2], (o[:, :2] @ i[:, 2] + o[:, 2])[:, None]])


def fit_affine(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares affine ``dst_from_src`` (2, 3) with ``dst ≈ A @ src``.

    Solves ``min_A sum_i w_i |A [src_i; 1] - dst_i|^2`` in float64 (exact for
    three or more non-collinear points related by an affine map).
    """
    src = np.asarray(src, np.float64).reshape(-1, 2)
    dst = np.asarray(dst, np.float64).reshape(-1, 2)
    x = np.hstack([src, np.ones((len(src), 1))])
    if weights is not None:
        w = np.sqrt(np.asarray(weights, np.float64))[:, None]
        x, dst = x * w, dst * w
    sol, *_ = np.linalg.lstsq(x, dst, rcond=None)
    return sol.T


def fit_similarity(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares similarity ``dst_from_src`` (2, 3) = ``[s R | t]``: rotation (no reflection), uniform
    scale, translation (Umeyama 1991; :func:`rigid_fit` with ``scale=True`` for one 2D frame). The map of
    the points alone is ``[:, :2]``; ``s`` is the norm of a column of it. Raises :class:`InputError` when
    the ``src`` points are all equal."""
    src = np.asarray(src, np.float64).reshape(-1, 2)
    dst = np.asarray(dst, np.float64).reshape(-1, 2)
    if ((src - src.mean(0)) ** 2).sum() < 1e-12:
        raise InputError("cannot fit a similarity: the source points are all equal")
    rot, trans, sc = rigid_fit(src, dst[None], scale=True)
    return np.hstack([sc[0] * rot[0], trans[0][:, None]])


def procrustes_mean(shapes: np.ndarray, n_iter: int = 10) -> np.ndarray:
    """Generalised Procrustes mean of ``shapes`` (n, n_points, 2): unit size, centred at the origin."""
    shapes = np.asarray(shapes, np.float64)
    ref = shapes[0] - shapes[0].mean(0)
    ref /= np.linalg.norm(ref)
    for _ in range(n_iter):
        rot, trans, sc = rigid_fit(shapes, np.broadcast_to(ref, shapes.shape), scale=True)
        aligned = sc[:, None, None] * np.einsum("fpj,fij->fpi", shapes, rot) + trans[:, None]
        new = aligned.mean(0)
        new -= new.mean(0)
        new /= np.linalg.norm(new)
        new = apply_affine(fit_similarity(new, ref), new)
        if np.abs(new - ref).max() < 1e-10:
            ref = new
            break
        ref = new
    return ref


def rigid_fit(ref: np.ndarray, frames: np.ndarray, weights: np.ndarray | None = None, scale: bool = False):
    """Weighted Kabsch/Umeyama fit of ``ref`` to every frame, vectorised over frames.

    Parameters
    ----------
    ref : (n_points, d) or (n_frames, n_points, d), d = 2 or 3
    frames : (n_frames, n_points, d), NaN allowed (such points get weight 0)
    weights : (n_points,) or (n_frames, n_points), optional
    scale : bool
        Also fit a uniform scale (Umeyama).

    Returns
    -------
    rot : (n_frames, d, d), trans : (n_frames, d), scale : (n_frames,)
        ``frames ~= scale * ref @ rot.T + trans``; frames with fewer than 3 usable points
        get NaN.
    """
    x = np.asarray(frames, dtype=np.float64)
    r = np.broadcast_to(np.asarray(ref, dtype=np.float64), x.shape)
    ok = np.isfinite(x).all(axis=2) & np.isfinite(r).all(axis=2)
    w = np.ones(x.shape[:2]) if weights is None else np.broadcast_to(np.asarray(weights, np.float64), x.shape[:2])
    w = np.where(ok, w, 0.0)
    x0 = np.where(ok[..., None], x, 0.0)
    r0 = np.where(ok[..., None], r, 0.0)
    ws = w.sum(axis=1)
    safe = np.maximum(ws, 1e-300)[:, None]
    mx = np.einsum("fp,fpc->fc", w, x0) / safe
    mr = np.einsum("fp,fpc->fc", w, r0) / safe
    xc = (x0 - mx[:, None]) * ok[..., None]
    rc = (r0 - mr[:, None]) * ok[..., None]
    cov = np.einsum("fp,fpi,fpj->fij", w, xc, rc)            # sum w x r^T
    u, s, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    dd = np.ones((len(x), x.shape[2]))
    dd[:, -1] = d
    rot = np.einsum("fij,fj,fjk->fik", u, dd, vt)
    if scale:
        var = np.einsum("fp,fpc,fpc->f", w, rc, rc)
        sc = np.einsum("fj,fj->f", s, dd) / np.maximum(var, 1e-300)
    else:
        sc = np.ones(len(x))
    trans = mx - sc[:, None] * np.einsum("fij,fj->fi", rot, mr)
    rank_ok = (ok & (w > 0)).sum(axis=1) >= x.shape[2]
    rot[~rank_ok] = np.nan
    trans[~rank_ok] = np.nan
    return rot, trans, sc


def apply_rigid(points: np.ndarray, rot: np.ndarray, trans: np.ndarray, inverse: bool = False) -> np.ndarray:
    """``points @ rot.T + trans`` per frame, or its inverse ``(points - trans) @ rot``."""
    if inverse:
        return np.einsum("fpj,fji->fpi", points - trans[:, None], rot)
    return np.einsum("fpj,fij->fpi", points, rot) + trans[:, None]


def _spans_a_plane(src: np.ndarray, dst: np.ndarray) -> bool:
    """RANSAC sample check: three points that are not (nearly) collinear fix a 3D rotation."""
    e1, e2 = src[1] - src[0], src[2] - src[0]
    return bool(np.linalg.norm(np.cross(e1, e2)) > 1e-9 * max(np.dot(e1, e1), np.dot(e2, e2), 1e-300))


def robust_rigid_fit(ref: np.ndarray, frames: np.ndarray, threshold: float, weights: np.ndarray | None = None,
                     max_trials: int = 200, seed: int = 0):
    """:func:`rigid_fit` that rejects the points of a frame that do not follow the others (3D).

    Every frame first gets the plain weighted least-squares fit. Only in a frame where some
    visible point lies further than ``threshold`` from its fitted position (and at least 4
    points are visible) are the outliers sought, by RANSAC (Fischler & Bolles 1981) over
    minimal 3-point samples with :func:`skimage.measure.ransac` and a 3D
    :class:`skimage.transform.EuclideanTransform`; the frame is then refitted by
    :func:`rigid_fit` (same weights) on the consensus set. Frames without a large residual
    keep the plain fit bit for bit, so a clean take costs one batched SVD.

    Parameters
    ----------
    ref : (n_points, 3) or (n_frames, n_points, 3)
    frames : (n_frames, n_points, 3), NaN allowed (hidden points are never "rejected")
    threshold : float
        Inlier distance, in the points' units (above the noise, below the faults to reject).
    weights : (n_points,) or (n_frames, n_points), optional
    max_trials, seed
        RANSAC samples per frame and its random seed (the same for every frame, so a frame's
        result does not depend on the others).

    Returns
    -------
    rot : (n_frames, 3, 3), trans : (n_frames, 3)
        ``frames ~= ref @ rot.T + trans`` on the inliers.
    rejected : (n_frames, n_points) bool
        Visible points left out of the fit as outliers.
    """
    x = np.asarray(frames, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"robust_rigid_fit: frames must be (n_frames, n_points, 3), got {x.shape}")
    r = np.broadcast_to(np.asarray(ref, dtype=np.float64), x.shape)
    w = np.ones(x.shape[:2]) if weights is None else np.broadcast_to(np.asarray(weights, np.float64), x.shape[:2])
    rot, trans, _ = rigid_fit(r, x, w)
    ok = np.isfinite(x).all(axis=2) & np.isfinite(r).all(axis=2) & (w > 0)
    res = np.linalg.norm(apply_rigid(r, rot, trans) - x, axis=2)
    suspect = (np.where(ok, res, 0.0) > threshold).any(axis=1) & (ok.sum(axis=1) >= 4)
    rejected = np.zeros(x.shape[:2], dtype=bool)
    if suspect.any():
        ransac, _Euclidean3D = _ransac_euclidean3d()
    for f in np.flatnonzero(suspect):              # the few frames with a fault; clean ones skip this
        vis = np.flatnonzero(ok[f])
        with warnings.catch_warnings():            # "No inliers found": handled below (plain fit kept)
            warnings.filterwarnings("ignore", message="No inliers found", category=UserWarning)
            model, inl = ransac((r[f, vis], x[f, vis]), _Euclidean3D, min_samples=3, residual_threshold=threshold,
                                is_data_valid=_spans_a_plane, max_trials=max_trials, stop_sample_num=len(vis),
                                stop_probability=0.9999, rng=seed)
        if model is not None and 3 <= inl.sum() < len(vis):
            rejected[f, vis[~inl]] = True
    redo = rejected.any(axis=1)
    if redo.any():
        rot[redo], trans[redo], _ = rigid_fit(r[redo], x[redo], np.where(rejected[redo], 0.0, w[redo]))
    return rot, trans, rejected


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (n_vertices, 3) (``np.bincount``, no loop over faces)."""
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = (v[triangles[:, k]] for k in range(3))
    fn = np.cross(b - a, c - a)
    idx = np.concatenate([triangles[:, 0], triangles[:, 1], triangles[:, 2]])
    n = np.stack([np.bincount(idx, np.tile(fn[:, d], 3), minlength=len(v)) for d in range(3)], axis=1)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
