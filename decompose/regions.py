"""Face regions, head-pose removal and per-region key shapes and weights.

Design notes and figures: docs/decompose.md, "Notes on the code", ``decompose/regions.py``.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.formats.keys import REGIONS, RegionKeys
from keyshape.base.formats.tracks import Tracks
from keyshape.base.schemes import Scheme
from keyshape.base.schemes import load_head_template
from keyshape.decompose.gaze import EYE_RADIUS_CM, pupil_points
from keyshape.decompose.head3d import HeadPose3D
from keyshape.decompose.defaults import HEAD_POSE
from keyshape.decompose.stabilize import HEAD_POSES, RigidStabilizer, stabilizer_from_entry

# the selectors and the solvers (scipy.fft, scipy.linalg) are imported where they are used: taking the
# head out of the tracks (retarget's head motion) does not need them, and the commands start faster

__all__ = ["REGIONS", "RegionKeys", "region_points", "available_regions", "head_pose", "model_shapes", "head_shapes",
           "stable_pose", "to_image", "select_region", "decompose_region", "face_rest_frame", "HEAD_POSES",
           "image_points", "head_points", "fitted_head_points", "head_pose_3d"]


def region_points(scheme: Scheme, region: str) -> np.ndarray:
    """Point indices of ``region`` (``mouth``, ``eyes`` or ``pupils``) in ``scheme``."""
    if region not in REGIONS:
        raise InputError(f"unknown region {region!r}: use one of {', '.join(REGIONS)}")
    parts = REGIONS[region].split("+")
    missing = [p for p in parts if p not in scheme.regions]
    if missing:
        raise InputError(f"scheme {scheme.name!r} lacks region(s) {', '.join(missing)} needed for "
                         f"{region!r}; it has {', '.join(scheme.regions)}")
    return scheme.region(REGIONS[region])


def available_regions(scheme: Scheme) -> list[str]:
    """The regions of :data:`REGIONS` that ``scheme`` can form."""
    return [r for r, parts in REGIONS.items() if all(p in scheme.regions for p in parts.split("+"))]


def head_pose(pose: np.ndarray) -> np.ndarray:
    """The head-motion part of ``image_from_model`` affines (..., 2, 3): the nearest similarity.

    ``[[a, -b], [b, a]]`` with ``a = (A_00 + A_11) / 2``, ``b = (A_10 - A_01) / 2`` (the Frobenius projection of
    ``A`` onto uniform scale and rotation), translation kept: the affine's shear moves with the expression.
    """
    pose = np.asarray(pose, dtype=np.float64)
    A = pose[..., :2]
    a = (A[..., 0, 0] + A[..., 1, 1]) / 2
    b = (A[..., 1, 0] - A[..., 0, 1]) / 2
    out = pose.copy()
    out[..., 0, 0] = out[..., 1, 1] = a
    out[..., 1, 0], out[..., 0, 1] = b, -b
    return out


def model_shapes(tracks: Tracks, path=None) -> np.ndarray:
    """Tracked points mapped to the model frame (head pose removed): (n_frames, n_points, 2).

    ``p_model = S^-1 (p_image - t)`` with ``[S | t] = head_pose(tracks.pose)``, the nearest
    similarity of the tracker's ``image_from_model`` (:func:`head_pose`).
    Failed frames (``success=0``) come back as NaN; NaN in a successful frame is an error.
    """
    pts = tracks.points
    ok = tracks.success
    bad = ok & ~np.isfinite(pts).all(axis=(1, 2))
    if bad.any():
        rows = np.flatnonzero(bad)
        raise InputError(f"frames {tracks.frame[rows[:5]].tolist()}{'...' if len(rows) > 5 else ''} are "
                         f"marked success=1 but have empty/NaN points: mark them success=0 or fill them", path)
    if np.any(np.abs(np.linalg.det(tracks.pose[ok, :, :2])) < 1e-12):
        raise InputError("a successful frame has a singular head pose (pose_a11..a22)", path)
    pose = head_pose(np.where(ok[:, None, None], tracks.pose, np.eye(2, 3)))
    A = pose[:, :, :2]
    if np.any(np.abs(np.linalg.det(A[ok])) < 1e-12):
        raise InputError("a successful frame's head pose has no rotation-and-scale part (pose_a11..a22)", path)
    Ainv = np.linalg.inv(np.where(ok[:, None, None], A, np.eye(2)))
    out = np.einsum("tij,tpj->tpi", Ainv, pts - pose[:, None, :, 2])
    out[~ok] = np.nan
    return out


def image_points(tracks: Tracks, path=None) -> np.ndarray:
    """The tracked image points (n_frames, n_points, 2), NaN in failed frames (checked as
    :func:`model_shapes` checks them)."""
    model_shapes(tracks, path)
    return np.where(tracks.success[:, None, None], tracks.points, np.nan)


def head_points(tracks: Tracks, scheme: Scheme, path=None) -> tuple[np.ndarray, Scheme]:
    """The image points the 3D head pose is fitted on and their scheme: :func:`image_points` followed by
    the tracks' auxiliary points (``Tracks.aux``, the nose) in :meth:`~keyshape.base.schemes.Scheme.full`
    ``scheme`` where the tracks carry all of its auxiliary groups; else :func:`image_points` and ``scheme``
    (tracks made before the nose points)."""
    pts = image_points(tracks, path)
    aux = scheme.auxiliary
    if not aux or scheme.n_core or not all(g in tracks.aux and tracks.aux[g].shape[1] == len(src)
                                           for g, src in aux.items()):
        return pts, scheme
    return _with_aux(pts, tracks, aux), scheme.full()


def _with_aux(pts: np.ndarray, tracks: Tracks, groups) -> np.ndarray:
    """``pts`` followed by the tracks' auxiliary points of ``groups`` (in that order), NaN on failed frames."""
    extra = np.concatenate([tracks.aux[g] for g in groups], axis=1)
    return np.concatenate([pts, np.where(tracks.success[:, None, None], extra, np.nan)], axis=1)


def fitted_head_points(head: HeadPose3D, tracks: Tracks, path=None) -> np.ndarray:
    """The image points of ``tracks`` a fitted ``head`` takes: :func:`image_points`, followed by the
    tracks' auxiliary points (in their order) where the head was fitted with them."""
    pts = image_points(tracks, path)
    n = len(head.template)
    if n > pts.shape[1] and tracks.aux:
        pts = _with_aux(pts, tracks, tracks.aux)
    if n > pts.shape[1]:
        raise InputError(f"the 3D head was fitted on {n} points (the scheme's and its nose points) but the tracks "
                         f"have {pts.shape[1]}: use tracks with the nose columns (nose_x_0..) of the model that "
                         "made the key set, or select the keys on these tracks", path)
    return pts[:, :n]


def head_pose_3d(scheme: Scheme, image_size: Sequence[int] | None = None) -> HeadPose3D | None:
    """An unfitted :class:`~keyshape.decompose.head3d.HeadPose3D` for ``scheme`` (its shipped 3D face
    and rigid points), or None when the scheme has no 3D face or no rigid points.

    ``image_size`` (width, height in pixels) puts the principal point at the image's centre,
    ``((w - 1) / 2, (h - 1) / 2)``; without it the estimator guesses it from the face. The scheme's pupils are
    frontalised on their eyeballs (``eyeballs``, radius :data:`~keyshape.decompose.gaze.EYE_RADIUS_CM`; Eq. 3 of
    :func:`~keyshape.decompose.head3d.frontalise`).
    """
    if not scheme.rigid:
        return None
    try:
        X, w = load_head_template(scheme)
    except InputError:
        return None
    if len(X) != scheme.n_points:
        return None
    centre = None
    if image_size is not None:
        centre = (np.asarray(image_size, np.float64)[:2] - 1.0) / 2.0
    return HeadPose3D(X, w, scheme.rigid, centre=centre, eyeballs=pupil_points(scheme), eye_radius=EYE_RADIUS_CM)


def head_shapes(tracks: Tracks, scheme: Scheme, head: str | dict | RigidStabilizer | HeadPose3D | None = HEAD_POSE,
                path=None) -> tuple[np.ndarray, RigidStabilizer | HeadPose3D | None]:
    """Shapes in the head frame (n_frames, n_points, 2) and the stabiliser that made them.

    Parameters
    ----------
    tracks, scheme : the tracks and their landmark scheme
    head : default :data:`~keyshape.decompose.defaults.HEAD_POSE`, as ``keyshape select``; ``"3d"``: the head's 3D pose taken out and the shapes brought to the front
        (:class:`~keyshape.decompose.head3d.HeadPose3D` fitted to this take's image points; ``rigid``
        where the scheme has no 3D face); ``"rigid"``: :func:`model_shapes` stabilised on ``scheme.rigid`` with a
        :class:`~keyshape.decompose.stabilize.RigidStabilizer` fitted to this take (the tracker's
        pose alone where the scheme names no rigid points); ``"tracker"`` or None: the tracker's
        pose alone; a fitted stabiliser, or a KEYS.json ``head_pose`` dict: that one (what
        ``keyshape decompose`` does with the stabiliser the keys were chosen with)
    path : the tracks file, named in errors

    Returns
    -------
    shapes, stabiliser (None for the tracker's pose alone)
    """
    if isinstance(head, dict):
        head = stabilizer_from_entry(head)
    if head == "3d":
        pts, full = head_points(tracks, scheme, path)
        head = head_pose_3d(full, tracks.image_size)
        if head is None:
            head = "rigid"
        else:
            head.fit(pts)
            # fit's own pose solve, not a second one; the scheme's points (the nose only poses the head)
            return head.transform(pts, head.camera_pose_)[:, :tracks.n_points], head
    if isinstance(head, HeadPose3D):
        return head.transform(fitted_head_points(head, tracks, path))[:, :tracks.n_points], head
    shapes = model_shapes(tracks, path)
    if head is None or head == "tracker":
        return shapes, None
    if head == "rigid":
        if not scheme.rigid:
            return shapes, None
        head = RigidStabilizer(scheme.rigid).fit(shapes)
    if not isinstance(head, RigidStabilizer):
        raise InputError(f"unknown head pose {head!r}: use one of {', '.join(HEAD_POSES)}")
    return head.transform(shapes), head


def stable_pose(tracks: Tracks, stabilizer: RigidStabilizer | dict | None, path=None) -> np.ndarray:
    """The head pose ``image_from_head`` (n_frames, 2, 3) that goes with :func:`head_shapes`:
    the tracker's nearest similarity composed with the inverse of the stabiliser's correction
    (``image = pose @ [shape; 1]`` for every frame). ``stabilizer`` may be a KEYS.json
    ``head_pose`` dict; None (or ``{"method": "tracker"}``): the tracker's pose alone. For the 3D head
    (:class:`~keyshape.decompose.head3d.HeadPose3D`) it is the 2D similarity nearest to the image on the
    rigid points (the 3D pose itself is :meth:`~keyshape.decompose.head3d.HeadPose3D.head_pose`)."""
    stabilizer = stabilizer_from_entry(stabilizer)
    if isinstance(stabilizer, HeadPose3D):
        return stabilizer.image_from_head(fitted_head_points(stabilizer, tracks, path))
    pose = head_pose(np.where(tracks.success[:, None, None], tracks.pose, np.eye(2, 3)))
    if stabilizer is None:
        return pose
    c = stabilizer.correction(model_shapes(tracks, path))           # stable_from_model
    inv = np.linalg.inv(c[:, :, :2])
    lin = np.einsum("tij,tjk->tik", pose[:, :, :2], inv)
    out = np.empty_like(pose)
    out[:, :, :2] = lin
    out[:, :, 2] = pose[:, :, 2] - np.einsum("tij,tj->ti", lin, c[:, :, 2])
    return out


def to_image(model_pts: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Model-frame points (n_frames, n, 2) to the image with the head part of ``pose`` (n_frames, 2, 3)
    (:func:`head_pose`: the inverse of :func:`model_shapes`)."""
    pose = head_pose(pose)
    return np.einsum("tij,tpj->tpi", pose[:, :, :2], model_pts) + pose[:, None, :, 2]


def select_region(tracks: Tracks, scheme: Scheme, region: str, n_keys: int | None, method: str = "spread",
                  rng=None, shapes: np.ndarray | None = None, neutral_frame: int | str | None = None,
                  progress: bool = False, rest_frame: int | None = None) -> RegionKeys:
    """Choose ``n_keys`` key shapes of ``region`` from the successful frames of ``tracks``.

    Failed frames (``success=0``) are never candidates. ``shapes`` may pass the
    already computed :func:`model_shapes`. The actor's neutral (``rest``) is always
    recorded: frame ``neutral_frame`` when it is a frame number, else frame ``rest_frame``
    when given (:func:`face_rest_frame`: one relaxed frame for all regions), else the
    region's most relaxed frame (:func:`relaxed_frame`). With ``neutral_frame`` given (a frame number or
    ``"auto"``) the weights are relative to that neutral; without it, to the take's mean
    (the paper's centring). :func:`drop_near_duplicates` then leaves out near-duplicate keys.
    """
    idx = region_points(scheme, region)
    shapes = model_shapes(tracks) if shapes is None else shapes
    ok = np.flatnonzero(tracks.success)
    if n_keys is not None and n_keys > len(ok):
        raise InputError(f"cannot choose {n_keys} key shapes from {len(ok)} successful frames "
                         f"({tracks.n_frames - len(ok)} of {tracks.n_frames} failed)")
    sub = shapes[ok][:, idx]
    wanted = rest_frame if neutral_frame is None or neutral_frame == "auto" else neutral_frame
    if wanted is None:
        row = int(ok[relaxed_frame(shapes[:, idx][ok])])
    else:
        hit = np.flatnonzero(tracks.frame == int(wanted))
        if not len(hit) or not tracks.success[hit[0]]:
            raise InputError(f"neutral frame {wanted} is not a successfully tracked frame of the tracks")
        row = int(hit[0])
    rest = shapes[row, idx].copy()
    # keys are chosen around the take's mean either way (measured: centring the greedy search on
    # the neutral frame gave worse rig curves on a synthetic take); only the weights' origin moves
    from keyshape.decompose.selectors import make_selector

    sel = make_selector(method, n_keys if n_keys is not None else 0, rng=rng, progress=progress,
                        desc=f"keyshape select {region}").fit(sub)
    from_frame = np.ones(len(sel.indices_), dtype=bool)
    if getattr(sel, "centre", "nearest") == "mean":
        from_frame[:] = False
    neutral = sel.neutral_ if neutral_frame is None else rest
    return RegionKeys(region, method, idx, tracks.frame[ok[sel.indices_]], sel.keys_, neutral, from_frame, rest,
                      int(tracks.frame[row]))


def drop_near_duplicates(rk: RegionKeys, min_distance: float) -> RegionKeys:
    """``rk`` without its near-duplicate keys: a key closer to an earlier key than ``min_distance`` times the
    median distance of the keys from the neutral ``rk.rest`` (RMS point distance) is left out (0 keeps all)."""
    if min_distance <= 0:
        return rk
    keep = near_duplicates(rk.keys, rk.rest, min_distance)
    return dataclasses.replace(rk, frames=rk.frames[keep], keys=rk.keys[keep], from_frame=rk.from_frame[keep])


def face_rest_frame(tracks: Tracks, shapes: np.ndarray, scheme: Scheme, regions) -> int:
    """The frame number of the actor's neutral for all of ``regions`` together: :func:`relaxed_frame`
    of the successful frames' points of every region at once (one frame for the whole face, so that one
    region's held or lopsided expression is not taken for the rest).
    """
    pts = np.unique(np.concatenate([region_points(scheme, r) for r in regions]))
    ok = np.flatnonzero(tracks.success)
    if not len(ok):
        raise InputError("no successful frame to take the neutral from")
    return int(tracks.frame[ok[relaxed_frame(shapes[ok][:, pts])]])


def near_duplicates(keys: np.ndarray, ref: np.ndarray, min_distance: float) -> np.ndarray:
    """Indices of the keys to keep: each key farther than ``min_distance`` x the median key-to-``ref``
    distance from every key kept before it (RMS point distances; a loop over keys, not frames)."""
    k = np.asarray(keys, float)
    rms = lambda a: np.sqrt((a ** 2).sum(-1).mean(-1))  # noqa: E731
    scale = float(np.median(rms(k - ref)))
    d = rms(k[:, None] - k[None])
    kept: list[int] = []
    for i in range(len(k)):
        if all(d[i, j] >= min_distance * scale for j in kept):
            kept.append(i)
    return np.array(kept, dtype=np.intp)


def relaxed_frame(shapes: np.ndarray, max_frames: int = 1500) -> int:
    """Row of the most relaxed frame of ``shapes`` (n_frames, n, 2): the densest, most typical shape.

    The shape with the smallest mean distance to its ``max(5, n / 10)`` nearest neighbours (the mode of the shape
    distribution); the wide neighbourhood keeps a held expression, a tight cluster of a few dozen frames, from
    winning. NaN rows are never chosen; at most ``max_frames`` evenly spaced rows are compared.
    """
    X = np.asarray(shapes, float).reshape(len(shapes), -1)
    ok = np.flatnonzero(np.isfinite(X).all(axis=1))
    if not len(ok):
        raise InputError("no successful frame to take the neutral from")
    rows = ok[np.linspace(0, len(ok) - 1, min(len(ok), max_frames)).round().astype(int)]
    rows = np.unique(rows)
    Y = X[rows]
    sq = (Y ** 2).sum(1)
    D = np.sqrt(np.maximum(sq[:, None] + sq[None] - 2 * Y @ Y.T, 0))
    k = min(max(5, len(rows) // 10), len(rows) - 1)
    if k < 1:
        return int(rows[0])
    score = np.sort(D, axis=1)[:, 1:k + 1].mean(axis=1)
    return int(rows[np.argmin(score)])


def decompose_region(tracks: Tracks, keys: RegionKeys, solver: str = "nnls", smooth_lambda: float = 0.1,
                     shapes: np.ndarray | None = None, ridge: float = 0.0) -> np.ndarray:
    """Weights (n_frames, n_keys) of ``keys`` for every frame of ``tracks``; failed frames interpolated."""
    shapes = model_shapes(tracks) if shapes is None else shapes
    if keys.points.max(initial=-1) >= shapes.shape[1]:
        raise InputError(f"key shapes of {keys.region!r} name point {keys.points.max()} but the tracks "
                         f"have {shapes.shape[1]} points")
    from keyshape.decompose.weights import solve_weights

    return solve_weights(shapes[:, keys.points], keys.keys, keys.neutral, solver=solver,
                         smooth_lambda=smooth_lambda, observed=tracks.success, ridge=ridge)
