"""A pose library: each key shape as a mix of an artist's rig shapes, and rig curves from key weights.

Section 5 of 004_119ba07521a9af0b.txt (Eq. 2) with each target a rig pose ``T_i = N + D p_i``: the rig is driven by
the curves ``c = p_n + W (P - p_n)`` (:func:`rig_curves`); :func:`fit_pose` suggests each ``p_i``.
Design notes and figures: docs/retarget.md, "Notes on the code", ``retarget/rig/poses.py``.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
from scipy.optimize import minimize

from keyshape.base.errors import InputError
from keyshape.base.geometry import fit_similarity
from keyshape.retarget.rig.model import mirror_pairs


def opposed_pairs(A: np.ndarray, free: np.ndarray | None = None, cosine: float = -0.5,
                  mirrored: Sequence[tuple[int, int]] = ()) -> list[tuple[int, int]]:
    """Pairs of rig shapes whose landmark motions point against each other (antagonists).

    Parameters
    ----------
    A : (m, n_shapes) landmark motion per unit of each shape (:func:`landmark_motion`)
    free : (m, k) nuisance motions, projected out of the columns first (what the fit ignores)
    cosine : pairs whose motions' cosine is below this are opposed (ARKit's browDown and browOuterUp
        of one side: -0.75; mouthLeft and mouthRight: -0.89; jawOpen and mouthClose: -0.99)
    mirrored : mirror-image pairs (:func:`~keyshape.retarget.rig.model.mirror_pairs`) that are opposed when their
        motions *before* the nuisances are projected out have a cosine below ``cosine``: a sideways
        pair (mouthLeft and mouthRight) opposes by its translation, which a free translation hides;
        both at once is then a narrowing of the lips no artist sculpts (it stood in for mouthPucker and
        mouthFunnel, docs/benchmarks.md)

    Returns
    -------
    list of (i, j), i < j
    """
    A = np.asarray(A, float)

    def cosines(M):
        norm = np.linalg.norm(M, axis=0)
        live = norm > 1e-12 * max(norm.max(initial=0.0), 1e-300)
        C = (M.T @ M) / np.outer(np.where(live, norm, 1.0), np.where(live, norm, 1.0))
        return np.where(live[:, None] & live[None, :], C, 0.0)

    raw = cosines(A)
    C = raw if free is None else cosines(A - free @ np.linalg.lstsq(free, A, rcond=None)[0])
    opposed = np.triu(C < cosine, 1)
    for i, j in mirrored:
        i, j = min(i, j), max(i, j)
        opposed[i, j] |= raw[i, j] < cosine
    i, j = np.nonzero(opposed)
    return list(zip(i.tolist(), j.tolist()))


def mirror_differences(mirrored: Sequence[tuple[int, int]], n: int) -> np.ndarray:
    """(len(mirrored), n) rows ``e_i - e_j`` of the mirrored pairs: ``|S p|^2 = sum (p_i - p_j)^2``, the
    left-right prior of :func:`fit_pose` and of ``keyshape solve`` (:class:`~keyshape.retarget.rig.solve.RigSolver`)."""
    S = np.zeros((len(mirrored), n))
    for r, (i, j) in enumerate(mirrored):
        S[r, i], S[r, j] = 1.0, -1.0
    return S


def fit_pose(A: np.ndarray, b: np.ndarray, bounds: tuple[float, float] = (0.0, 1.0),
             sparsity: float = 0.02, scale: float | None = None, free: np.ndarray | None = None,
             exclusive: Sequence[tuple[int, int]] = (), symmetry: float = 0.0,
             mirrored: Sequence[tuple[int, int]] = ()) -> np.ndarray:
    """Bounded, sparse least squares with a left-right prior:
    ``argmin ||A p + F q - b||^2 / scale^2 + sparsity * sum_j p_j + symmetry * a * sum_(i,j) (p_i - p_j)^2``.

    Parameters
    ----------
    A : (m, n_shapes) motion of the landmarks (flattened) per unit of each rig shape, in the
        same frame and units as ``b``
    b : (m,) the key's landmark motion from the neutral
    bounds : the shapes' range ``[lo, hi]`` with ``lo >= 0`` (so the L1 term is linear)
    sparsity : weight of the L1 term on the rig weights (0: plain bounded least squares). Every
        unit of rig weight costs the same, the usual blendshape-solver prior: fewer, stronger
        shapes are preferred to many weak ones that together move the points alike
    scale : size of a typical key motion (default ``||b||``); a common scale for all keys of a
        region keeps a key that barely moves (noise) at the rest pose instead of fitting its noise
    free : (m, k) nuisance motions with unbounded, unpenalised coefficients ``q`` (e.g. a common
        translation of the region's points, which 2D head-pose removal leaves behind)
    exclusive : pairs of shapes that may not both be used (:func:`opposed_pairs`). Two opposed
        shapes together cancel in the 2D points but not on the mesh (a brow pulled down and
        raised at once: a frown the actor never made); while a pair is both on, the pair's
        weaker use (the smaller of the two weights) is settled by refitting without either shape
        and keeping the better fit, one shape of the pair dropped
    symmetry : dimensionless weight of the left-right prior over the ``mirrored`` pairs (``a`` is the
        mean squared column norm of ``A / scale``, so the prior does not depend on units): a face is
        near symmetric, and a 2D fit can trade one side's shape for the other's neighbours (a smile
        fitted as mouthSmile_L with mouthStretch_R). The same prior as ``keyshape solve``'s
        (:class:`~keyshape.retarget.rig.solve.RigSolver`); a one-sided key still fits one-sided
    mirrored : mirror-image shape pairs (:func:`~keyshape.retarget.rig.model.mirror_pairs`)

    Returns
    -------
    (n_shapes,) weights within ``bounds`` (``q`` is not returned).
    """
    A, b = np.asarray(A, float), np.asarray(b, float)
    lo, hi = bounds
    if lo < 0:
        raise InputError(f"fit_pose needs a non-negative range, got {bounds}")
    n = A.shape[1]
    if n == 0:
        return np.zeros(0)
    scale = float(np.linalg.norm(b)) if scale is None else float(scale)
    if scale < 1e-12:
        return np.zeros(n)
    F = np.zeros((len(b), 0)) if free is None else np.asarray(free, float)
    k = F.shape[1]
    As = np.hstack([A, F]) / scale                         # keep the objective O(1)
    bs = b / scale
    G, h, c = As.T @ As, As.T @ bs, float(bs @ bs)
    if len(mirrored) and symmetry > 0:
        S = mirror_differences(mirrored, n + k)
        G = G + symmetry * float(np.mean((As[:, :n] ** 2).sum(axis=0))) * S.T @ S
    l1 = np.concatenate([np.full(n, sparsity), np.zeros(k)])

    def f(x):
        Gx = G @ x
        return x @ Gx - 2 * h @ x + c + l1 @ x, 2 * (Gx - h) + l1

    def solve(off):
        """Minimise with the shapes in ``off`` held at ``lo``; returns (weights, objective)."""
        box = [(lo, lo) if o else (lo, hi) for o in off] + [(None, None)] * k
        x0 = np.concatenate([np.full(n, lo), np.zeros(k)])
        res = minimize(f, x0, jac=True, method="L-BFGS-B", bounds=box,
                       options={"maxiter": 5000, "ftol": 1e-15, "gtol": 1e-11})
        p = np.clip(res.x[:n], lo, hi)
        p[p < lo + 1e-4 * (hi - lo)] = lo
        return p, float(res.fun)

    off = np.zeros(n, dtype=bool)
    p, _ = solve(off)
    pairs = [(int(i), int(j)) for i, j in exclusive]
    for _ in range(len(pairs)):
        both = [(i, j) for i, j in pairs if p[i] > lo and p[j] > lo]
        if not both:
            break
        i, j = max(both, key=lambda ij: min(p[ij[0]], p[ij[1]]))
        tries = []
        for drop in (i, j):
            o = off.copy()
            o[drop] = True
            tries.append((*solve(o), o))
        p, _, off = min(tries, key=lambda t: t[1])
    return p


def landmark_motion(deltas_2d: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(2 * len(points), n_shapes) matrix ``A`` of :func:`fit_pose` from per-shape 2D point motion."""
    return deltas_2d[:, points].reshape(len(deltas_2d), -1).T


def rig_curves(weights: np.ndarray, poses: np.ndarray, neutral_pose: np.ndarray | None = None,
               bounds: tuple[float, float] | None = (0.0, 1.0)) -> np.ndarray:
    """Rig curves from key weights: ``c = p_n + W (P - p_n)``, clipped to the rig's range.

    Parameters
    ----------
    weights : (n_frames, n_keys) key-shape weights (``keyshape decompose``)
    poses : (n_keys, n_shapes) each key's rig pose
    neutral_pose : (n_shapes,) pose of the shape the weights are relative to (default 0)
    bounds : clip to this range (None: no clipping)

    Returns
    -------
    (n_frames, n_shapes)
    """
    W = np.asarray(weights, float)
    P = np.asarray(poses, float)
    if W.ndim != 2 or P.ndim != 2 or W.shape[1] != P.shape[0]:
        raise InputError(f"weights {W.shape} and poses {P.shape} do not match (n_keys)")
    pn = np.zeros(P.shape[1]) if neutral_pose is None else np.asarray(neutral_pose, float)
    c = pn + W @ (P - pn)
    return c if bounds is None else np.clip(c, *bounds)


def pose_vector(pose: Mapping[str, float], names: Sequence[str]) -> np.ndarray:
    """A pose ``{shape: weight}`` as weights over ``names`` (shapes it does not name at 0)."""
    p = np.zeros(len(names))
    for s, v in pose.items():
        p[list(names).index(s)] = v
    return p


def curves_from_library(weights: np.ndarray, columns: Sequence[str], library: Mapping,
                        shape_names: Sequence[str], source=None) -> np.ndarray:
    """Rig curves (n_frames, n_shapes) for weight ``columns`` from a pose library dict (POSES.json layout).

    Each region's keys drive only that region's shapes; shapes of no region stay 0.
    Raises :class:`InputError` (naming ``source``) for a column without a pose.
    """
    index = {n: j for j, n in enumerate(shape_names)}
    W = np.asarray(weights, float)
    out = np.zeros((len(W), len(shape_names)))
    lo, hi = library.get("range", (0.0, 1.0))
    col = {c: i for i, c in enumerate(columns)}
    known = {k for reg in library["regions"].values() for k in reg["keys"]}
    missing = [c for c in columns if c not in known]
    if missing:
        raise InputError(f"weight column(s) {missing[:5]} have no pose in the pose library", source)
    for r, reg in library["regions"].items():
        keys = [k for k in reg["keys"] if k in col]
        if not keys:
            continue
        shapes = [index[s] for s in reg["shapes"]]
        P = np.array([pose_vector(reg["keys"][k], reg["shapes"]) for k in keys]).reshape(len(keys), len(shapes))
        pn = pose_vector(reg.get("neutral", {}), reg["shapes"])
        out[:, shapes] += rig_curves(W[:, [col[k] for k in keys]], P, pn, None)
    return np.clip(out, lo, hi)


def nuisance_motions(points: np.ndarray, kind: str = "translation") -> np.ndarray | None:
    """(2n, k) flattened motions of ``points`` (n, 2) a pose fit ignores: ``"none"`` (None),
    ``"translation"`` (k=2) or ``"similarity"`` (k=4: translation, scale and rotation about the centroid)."""
    if kind == "none":
        return None
    n = len(points)
    cols = [np.tile([1.0, 0.0], n), np.tile([0.0, 1.0], n)]
    if kind == "similarity":
        c = points - points.mean(axis=0)
        cols += [c.ravel(), np.stack([-c[:, 1], c[:, 0]], 1).ravel()]
    elif kind != "translation":
        raise InputError(f"unknown nuisance {kind!r}: use none, translation or similarity")
    return np.stack(cols, axis=1)


def auto_nuisance(region: str, stabilized: bool) -> str:
    """The ``auto`` nuisance of a region: ``translation`` for the mouth (it moves against the eye corners with head
    pitch and yaw, which no 2D stabilisation removes); for the other regions ``none`` when the keys' head was
    stabilised on rigid points, else ``similarity``.
    """
    if region == "mouth":
        return "translation"
    return "none" if stabilized else "similarity"


def pose_library(regions, shape_names: Sequence[str], landmark_neutral: np.ndarray, landmark_deltas: np.ndarray,
                 region_shapes: Mapping[str, np.ndarray], bounds: tuple[float, float] = (0.0, 1.0),
                 sparsity: float = 0.01, nuisance: str | Mapping[str, str] = "auto",
                 exclusive: float | None = -0.5, symmetry: float = 0.03) -> dict:
    """Suggest a rig pose for every key of every region (the ``regions`` part of POSES.json).

    Parameters
    ----------
    regions : list of :class:`~keyshape.decompose.regions.RegionKeys` (model frame), each with ``rest``
        (the actor's neutral; the region's ``neutral`` is used when it has none)
    shape_names : the rig's shape names
    landmark_neutral : (n_points, 2) the rig's neutral scheme points, projected (:func:`~keyshape.retarget.rig.model.project`)
    landmark_deltas : (n_shapes, n_points, 2) projected motion of the scheme points per rig shape
    region_shapes : {region: indices of the rig shapes it may drive} (:func:`~keyshape.retarget.rig.model.shape_regions`)
    bounds, sparsity : see :func:`fit_pose`; the L1 scale is the region's largest key motion
    nuisance : "auto" (default), "translation", "similarity" or "none", or a dict of them per
        region: motions of each region's points fitted freely besides the rig shapes
        (:func:`nuisance_motions`); "auto" is :func:`auto_nuisance` for a head not stabilised on rigid
        points (:func:`~keyshape.retarget.api.fit_poses` resolves it per region from the keys' ``head_pose``)
    exclusive : shapes of a region whose landmark motions (nuisances projected out) have a cosine
        below this are never used together in one pose (:func:`opposed_pairs`, :func:`fit_pose`);
        None allows every combination; mirror-image pairs opposed before the nuisances are projected
        out (mouthLeft and mouthRight) count too
    symmetry : weight of the left-right prior over the region's mirror-image shapes (:func:`fit_pose`)

    Returns
    -------
    dict ``{region: {"shapes": [...], "neutral": {shape: w}, "keys": {key: {shape: w}}}}`` plus, under
    ``"_fit"``, per key the relative residual ``||A p - b|| / ||b||`` of the fit.

    Notes
    -----
    The actor's 2D motion is mapped into the rig's frame by the similarity that best
    maps the actor's neutral points (all regions together) onto the rig's neutral
    points (:func:`~keyshape.base.geometry.fit_similarity`); each key's pose then solves :func:`fit_pose` on its
    region's points.
    """
    rest = {rk.region: (rk.rest if rk.rest is not None else rk.neutral) for rk in regions}
    pts = np.concatenate([rk.points for rk in regions])
    src = np.concatenate([rest[rk.region] for rk in regions])
    M = fit_similarity(src, landmark_neutral[pts])[:, :2]      # s R: the actor's motion in the rig's frame
    out: dict = {}
    fit: dict = {}
    for rk in regions:
        shapes = np.asarray(region_shapes.get(rk.region, []), dtype=np.intp)
        names = [shape_names[j] for j in shapes]
        A = landmark_motion(landmark_deltas[shapes], rk.points) if len(shapes) else np.zeros((2 * len(rk.points), 0))
        kind = nuisance.get(rk.region, "auto") if isinstance(nuisance, Mapping) else nuisance
        kind = auto_nuisance(rk.region, False) if kind == "auto" else kind
        F = nuisance_motions(rest[rk.region] @ M.T, kind)
        mirrored = mirror_pairs(names)
        pairs = opposed_pairs(A, F, exclusive, mirrored) if exclusive is not None and len(shapes) else []
        motions = [((x - rest[rk.region]) @ M.T).ravel() for x in [*rk.keys, rk.neutral]]
        scale = max(float(np.linalg.norm(m)) for m in motions)
        entry = {"shapes": names, "neutral": {}, "keys": {}}

        def solve(b):
            p = fit_pose(A, b, bounds, sparsity, scale, F, pairs, symmetry, mirrored)
            r = A @ p - b
            if F is not None:
                r = r - F @ np.linalg.lstsq(F, r, rcond=None)[0]
            res = float(np.linalg.norm(r) / max(np.linalg.norm(b), 1e-12))
            return {names[j]: float(p[j]) for j in np.flatnonzero(p)}, res

        if rk.rest is not None and np.abs(rk.neutral - rk.rest).max() > 1e-9:
            entry["neutral"], fit[f"{rk.region}_neutral"] = solve(motions[-1])
        for name, b in zip(rk.names, motions[:-1]):
            entry["keys"][name], fit[name] = solve(b)
        out[rk.region] = entry
    out["_fit"] = fit
    return out
