"""The retarget stage's part of the Python API (:mod:`keyshape.api`).

``keyshape retarget`` (``retarget/cli.py``), :mod:`keyshape.api` and ``keyshape batch`` all call
these functions: fit a :class:`~keyshape.retarget.retargeter.Retargeter` to target key shapes
(files or a :class:`~keyshape.retarget.targets.TargetSet`) and turn tracks into head motion.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.formats.tracks import Tracks
from keyshape.retarget.headpose import HeadMotion, head_motion, hold_invalid
from keyshape.retarget.retargeter import Retargeter
from keyshape.retarget.targets import TargetSet, load_targets, read_regions


def fit_retargeter(columns: Sequence[str], targets, regions=None, mapping=None, neutral=None, form: str = "auto",
                   band: float | None = None, metric: str = "geodesic") -> Retargeter:
    """A :class:`Retargeter` fitted to one target per weight column.

    Parameters
    ----------
    columns : the weight columns (``REGION_K``) in order
    targets : a :class:`TargetSet`, a folder or a list of target files (see
        :func:`~keyshape.retarget.targets.load_targets`)
    regions : ``{region: vertex indices}``, or a regions JSON / grouped OBJ file, or None
    mapping, neutral : as :func:`~keyshape.retarget.targets.load_targets` (files only)
    form, band, metric : as :class:`Retargeter`
    """
    if isinstance(targets, TargetSet):
        ts = targets
    else:
        if isinstance(targets, (list, tuple)) and len(targets) == 1:
            targets = targets[0]
        ts = load_targets(list(columns), targets, mapping=mapping, neutral=neutral)
    source = "regions"
    if isinstance(regions, (str, Path)):
        source = str(regions)
        regions = read_regions(regions, ts.mesh)
    return Retargeter(form=form, band=band, metric=metric).fit(ts, regions, source)


def head_from_tracks(tracks: Tracks, frames: np.ndarray, reference_frame: int | None = None, head_units: float = 1.0,
                     source=None, head: str | dict = "3d") -> tuple[HeadMotion, float | None]:
    """Head motion of the weights' ``frames`` from the tracks' 2D pose, and the tracks' frame rate.

    ``head``: ``3d`` (default): the head's 3D pose (:class:`~keyshape.decompose.head3d.HeadPose3D`
    fitted to the tracks, or the one of a KEYS.json ``head_pose`` entry given as a dict): rotation
    about the rig's origin and translation with depth (:func:`~keyshape.retarget.headpose.head_motion_3d`),
    zero at the estimator's most front-facing relaxed frame unless ``reference_frame`` is given, the
    translation in model units (the actor's inter-ocular distance in the model frame per the 3D
    face's) times ``head_units``; ``rigid`` where the scheme has no 3D face. ``rigid``: the tracker's pose stabilised on the scheme's rigid points
    (:func:`~keyshape.decompose.regions.stable_pose`), so that an expression the tracker's pose
    took up does not move the character's head; ``tracker``: the tracker's pose as it is (also
    for tracks of a point count no built-in scheme has). Failed frames hold the last good pose.
    ``reference_frame``: the frame of the rest pose (2D default: the first frame).
    The frame rate is the median of the timestamps' steps (None when they do not give one).
    """
    pos = {int(f): i for i, f in enumerate(tracks.frame)}
    missing = [int(f) for f in frames if int(f) not in pos]
    if missing:
        raise InputError(f"weights frames {missing[:5]} are not in the tracks", source)
    rows = np.array([pos[int(f)] for f in frames])
    if reference_frame is not None and reference_frame not in pos:
        raise InputError(f"reference frame {reference_frame} is not in the tracks", source)
    from keyshape.decompose.stabilize import HEAD_POSES
    from keyshape.decompose.head3d import HeadPose3D
    if isinstance(head, dict):
        head = head if head.get("method") == "3d" else head.get("method", "tracker")
    if not isinstance(head, (dict, HeadPose3D)) and head not in HEAD_POSES:
        raise InputError(f"unknown head pose {head!r}: use one of {', '.join(HEAD_POSES)}")
    fps = None
    if len(tracks.time) > 1:
        dt = np.diff(tracks.time)
        dt = dt[np.isfinite(dt) & (dt > 0)]
        fps = round(float(1.0 / np.median(dt)), 3) if len(dt) else None
    if (isinstance(head, (dict, HeadPose3D)) or head == "3d") and tracks.success.any():
        motion = _head_3d(tracks, head, rows, None if reference_frame is None else pos[reference_frame],
                          head_units, source)
        if motion is not None:
            return motion, fps
        head = "rigid"
    if reference_frame is None:
        reference_frame = int(tracks.frame[0])
    pose = tracks.pose
    if head == "rigid" and tracks.success.any():
        from keyshape.base.schemes import scheme_for_n_points
        from keyshape.decompose.regions import head_shapes, stable_pose
        try:
            scheme = scheme_for_n_points(tracks.n_points)
        except InputError:                     # no built-in scheme, no rigid points: the tracker's pose
            scheme = None
        if scheme is not None and scheme.rigid:
            _, stab = head_shapes(tracks, scheme, "rigid", source)
            pose = np.where(tracks.success[:, None, None], stable_pose(tracks, stab, source), tracks.pose)
    full = hold_invalid(pose, tracks.success)
    pose = np.concatenate([full[rows], full[[pos[reference_frame]]]])
    head = head_motion(pose, reference=len(rows), units_per_model=head_units)
    head = head.take(slice(0, -1))
    return head, fps


def _head_3d(tracks: Tracks, head, rows: np.ndarray, ref_row: int | None, head_units: float, source):
    """The 3D head's motion of ``rows`` (None where the tracks' scheme has no 3D face)."""
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.decompose.regions import head_pose_3d, image_points, model_shapes
    from keyshape.decompose.stabilize import stabilizer_from_entry
    from keyshape.retarget.headpose import head_motion_3d
    try:
        scheme = scheme_for_n_points(tracks.n_points)
    except InputError:
        return None
    from keyshape.decompose.head3d import HeadPose3D
    pts = image_points(tracks, source)
    if isinstance(head, (dict, HeadPose3D)):
        est = stabilizer_from_entry(head)
    else:
        est = head_pose_3d(scheme)
        if est is None:
            return None
        est.fit(pts)
    hp = est.head_pose(pts)
    R, t = hp["rotation"], hp["translation"]
    if ref_row is not None and np.isfinite(R[ref_row]).all():
        from keyshape.decompose.head3d import euler_angles
        R = np.einsum("tij,kj->tik", R, R[ref_row])
        t = t - t[ref_row]
        ang = euler_angles(R)
    else:
        ang = hp["angles"]
    a, b = scheme.inter_ocular
    ms = model_shapes(tracks, source)[tracks.success]
    iod_model = float(np.median(scheme.interocular_distance(ms)))
    iod_face = float(np.linalg.norm(est.template_[a] - est.template_[b]))
    return head_motion_3d(R, t, ang, head_units * iod_model / iod_face).take(rows)


def head_3d_from_tracks(tracks: Tracks, source=None):
    """The :class:`~keyshape.decompose.head3d.HeadPose3D` fitted to ``tracks`` (None where their scheme
    has no 3D face): give it to :func:`head_from_tracks` and :func:`gaze_from_tracks` to fit once."""
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.decompose.regions import head_pose_3d, image_points
    try:
        scheme = scheme_for_n_points(tracks.n_points)
    except InputError:
        return None
    est = head_pose_3d(scheme)
    return None if est is None or not tracks.success.any() else est.fit(image_points(tracks, source))


def gaze_from_tracks(tracks: Tracks, frames: np.ndarray, head=None, source=None) -> np.ndarray:
    """(n_frames, 4) eye angles of the weights' ``frames`` (left yaw, left pitch, right yaw, right pitch,
    radians; :func:`keyshape.decompose.gaze.gaze_angles`) from the pupils in the head's frame (``head``:
    a fitted :class:`~keyshape.decompose.head3d.HeadPose3D`, a KEYS.json ``head_pose`` entry, or None:
    fitted here; the 2D rigid head where the scheme has no 3D face). Failed frames hold the last good
    gaze. Raises :class:`InputError` when the scheme has no pupils."""
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.decompose.gaze import gaze_angles
    from keyshape.decompose.regions import head_shapes
    scheme = scheme_for_n_points(tracks.n_points)
    shapes, _ = head_shapes(tracks, scheme, "3d" if head is None else head, source)
    g = gaze_angles(shapes, scheme)
    pos = {int(f): i for i, f in enumerate(tracks.frame)}
    missing = [int(f) for f in frames if int(f) not in pos]
    if missing:
        raise InputError(f"weights frames {missing[:5]} are not in the tracks", source)
    ok = np.isfinite(g).all(axis=1)
    if ok.any():
        idx = np.maximum.accumulate(np.where(ok, np.arange(len(g)), -1))
        idx[idx < 0] = int(np.flatnonzero(ok)[0])
        g = g[idx]
    return np.nan_to_num(g[[pos[int(f)] for f in frames]])
