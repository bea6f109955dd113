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


def head_from_tracks(tracks: Tracks, frames: np.ndarray, reference_frame: int = 0, head_units: float = 1.0,
                     source=None, head: str = "rigid") -> tuple[HeadMotion, float | None]:
    """Head motion of the weights' ``frames`` from the tracks' 2D pose, and the tracks' frame rate.

    ``head``: ``rigid`` (default): the tracker's pose stabilised on the scheme's rigid points
    (:func:`~keyshape.decompose.regions.stable_pose`), so that an expression the tracker's pose
    took up does not move the character's head; ``tracker``: the tracker's pose as it is (also
    for tracks of a point count no built-in scheme has). Failed frames hold the last good pose.
    The frame rate is the median of the timestamps' steps (None when they do not give one).
    """
    pos = {int(f): i for i, f in enumerate(tracks.frame)}
    missing = [int(f) for f in frames if int(f) not in pos]
    if missing:
        raise InputError(f"weights frames {missing[:5]} are not in the tracks", source)
    rows = np.array([pos[int(f)] for f in frames])
    if reference_frame not in pos:
        raise InputError(f"reference frame {reference_frame} is not in the tracks", source)
    from keyshape.decompose.stabilize import HEAD_POSES
    if head not in HEAD_POSES:
        raise InputError(f"unknown head pose {head!r}: use one of {', '.join(HEAD_POSES)}")
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
    head = type(head)(head.translation[:-1], head.rotation[:-1], head.scale[:-1], head.angle[:-1])
    fps = None
    if len(tracks.time) > 1:
        dt = np.diff(tracks.time)
        dt = dt[np.isfinite(dt) & (dt > 0)]
        fps = round(float(1.0 / np.median(dt)), 3) if len(dt) else None
    return head, fps
