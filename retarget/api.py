"""The retarget stage's in-memory layer, with the product's defaults.

Design notes and figures: docs/retarget.md, "Notes on the code", ``retarget/api.py``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.formats.tracks import Tracks
from keyshape.decompose.take import Take
from keyshape.retarget.headpose import HeadMotion, head_motion, hold_invalid
from keyshape.retarget.targets.retargeter import Retargeter
from keyshape.retarget.targets.target_set import TargetSet, load_targets, read_regions

from keyshape.retarget.defaults import (DEFAULT_FPS, FORM, GAZE, GAZES, HEAD_MOTION, METRIC, NUISANCE,  # noqa: F401,E402
                                        OPPOSED, SPARSITY, SYMMETRY, RetargetOptions, SolveOptions)


def fit_retargeter(columns: Sequence[str], targets, regions=None, mapping=None, neutral=None, form: str = FORM,
                   band: float | None = None, metric: str = METRIC) -> Retargeter:
    """A :class:`Retargeter` fitted to one target per weight column.

    Parameters
    ----------
    columns : the weight columns (``REGION_K``) in order
    targets : a :class:`TargetSet`, a folder or a list of target files (see
        :func:`~keyshape.retarget.targets.target_set.load_targets`)
    regions : ``{region: vertex indices}``, a regions JSON / grouped OBJ file, ``"auto"`` (from the
        targets' own support: each vertex to the region whose targets move it most; needs a
        neutral), or None
    mapping, neutral : as :func:`~keyshape.retarget.targets.target_set.load_targets` (files only)
    form, band, metric : as :class:`Retargeter`
    """
    if isinstance(targets, TargetSet):
        ts = targets
    else:
        ts = load_targets(list(columns), targets, mapping=mapping, neutral=neutral)
    source = "regions"
    if isinstance(regions, str) and regions == "auto":
        from keyshape.retarget.rig.model import support_regions
        if ts.neutral is None:
            raise InputError("--regions auto needs a neutral (--neutral or neutral.* among the targets)")
        regions = support_regions(ts.shapes, ts.neutral, ts.columns)
        source = "regions auto"
    elif isinstance(regions, (str, Path)):
        source = str(regions)
        regions = read_regions(regions, ts.mesh)
    return Retargeter(form=form, band=band, metric=metric).fit(ts, regions, source)


def take_head(take: Take, frames: np.ndarray, rig=None, options: RetargetOptions = RetargetOptions(), say=None):
    """The head motion of ``frames`` written beside the curves (``keyshape retarget --tracks``, the API's retarget)
    and the head the gaze is read in: the take's fitted 3D head where ``options.head`` is ``3d``, else the 2D kind.
    The translation's units: ``options.head_units``, else with a ``rig`` its inter-ocular distance over the actor's
    (said through ``say``), else 1."""
    units = options.head_units
    if units is None:
        units = 1.0 if rig is None else rig_head_units(rig, take.tracks, options.landmarks)
        if rig is not None and say is not None:
            say(f"head translation in rig units: {units:.4g} rig units per model unit (rig inter-ocular distance / "
                "actor's)")
    kind = take.head3d if options.head == "3d" and take.head3d is not None else options.head
    return head_from_tracks(take.tracks, frames, options.reference_frame, units, take.source, head=kind), kind


def take_motion(tracks: Tracks | None, frames: np.ndarray, weights_fps: float | None = None, rig=None,
                options: RetargetOptions = RetargetOptions(), source=None, say=None):
    """``(head motion of frames or None, frame rate, the head the gaze is read in or None)`` of a take's ``tracks``
    (None: no head): :func:`take_head` on the take fitted once, and :func:`~keyshape.decompose.take.take_fps` (the
    tracks' rate, else the weights' ``weights_fps``, else 30)."""
    from keyshape.decompose.take import take_fps
    if tracks is None:
        return None, take_fps(None, weights_fps), None
    head, kind = take_head(Take.fit(tracks, source), frames, rig, options, say)
    return head, take_fps(tracks, weights_fps), kind


def head_from_tracks(tracks: Tracks, frames: np.ndarray, reference_frame: int | None = None, head_units: float = 1.0,
                     source=None, head: str | dict = HEAD_MOTION) -> HeadMotion:
    """Head motion of the weights' ``frames`` from the tracks' pose.

    ``head_units``: model units to mesh units of the translation.

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
    if (isinstance(head, (dict, HeadPose3D)) or head == "3d") and tracks.success.any():
        motion = _head_3d(tracks, head, rows, None if reference_frame is None else pos[reference_frame],
                          head_units, source)
        if motion is not None:
            return motion
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
    return head_motion(pose, reference=len(rows), units_per_model=head_units).take(slice(0, -1))


def rig_head_units(rig, tracks: Tracks, landmarks=None) -> float:
    """Rig units per tracker model unit: the rig's inter-ocular distance over the actor's (median, model frame)."""
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.decompose.regions import model_shapes
    from keyshape.retarget.rig.model import rig_landmarks

    scheme = scheme_for_n_points(tracks.n_points)
    W, _ = rig_landmarks(rig, scheme.name, landmarks)
    a, b = scheme.inter_ocular
    rig_iod = float(np.linalg.norm((W[a] - W[b]) @ rig.neutral))
    iod = scheme.interocular_distance(model_shapes(tracks)[tracks.success])
    return rig_iod / float(np.median(iod))


def fit_poses(regions, scheme_name: str, rig, head_pose: dict | None = None, landmarks=None,
              sparsity: float = SPARSITY, nuisance: str = NUISANCE, opposed: float = OPPOSED,
              symmetry: float = SYMMETRY) -> tuple[dict, dict]:
    """Suggest every key's pose on ``rig`` (``keyshape pose``): the pose library and each fit's residual.

    Parameters
    ----------
    regions : the keys' :class:`~keyshape.decompose.regions.RegionKeys` (model frame)
    scheme_name : their landmark scheme
    rig : a :class:`~keyshape.retarget.rig.model.Rig`
    head_pose : the keys' KEYS.json ``head_pose`` entry (rigid stabilisation frees fewer nuisances)
    landmarks : rig landmark JSON (default: the shipped one for ICT-FaceKit rigs)
    sparsity, nuisance, opposed, symmetry : see :func:`~keyshape.retarget.rig.poses.pose_library`

    Returns
    -------
    ``(library, residuals)``: the library in POSES.json's layout (``rig``, ``range``, ``regions``;
    the caller adds ``keys``), and per key (and region neutral) the relative residual
    ``||A p - b|| / ||b||`` of its landmark motion.
    """
    from keyshape.base.schemes import load_scheme
    from keyshape.retarget.rig.poses import auto_nuisance, pose_library

    if not (np.isfinite(opposed) and -1.0 <= opposed <= 0.0):
        raise InputError(f"--opposed {opposed}: a cosine from -1 to 0")
    check_solve_options(sparsity, symmetry, 0.0)
    scheme = load_scheme(scheme_name)
    lm_neutral, lm_deltas, reg_shapes, lm_path = _rig_points(rig, scheme, scheme_name, landmarks)
    stabilized = (head_pose or {}).get("method") in ("rigid", "3d")
    if (head_pose or {}).get("method") == "rigid":
        # the keys' eye corners were held still: read the rig's motion in that frame too (as keyshape solve does)
        from keyshape.decompose.gaze import pupil_points
        from keyshape.retarget.rig.solve import rigid_frame_deltas
        lm_deltas = rigid_frame_deltas(lm_neutral, lm_deltas, head_pose.get("points", ()), keep=pupil_points(scheme))
    if nuisance == "auto":
        nuisance = {rk.region: auto_nuisance(rk.region, stabilized) for rk in regions}
    lib = pose_library(regions, rig.names, lm_neutral, lm_deltas, reg_shapes, rig.value_range, sparsity, nuisance,
                       opposed, symmetry)
    fit = lib.pop("_fit")
    data = {"rig": {"neutral": str(rig.neutral_file), "n_vertices": rig.n_vertices, "shapes": list(rig.names),
                    "landmarks": str(lm_path)},
            "range": list(rig.value_range), "regions": lib}
    return data, fit


def _rig_points(rig, scheme, scheme_name: str, landmarks):
    """The rig's scheme points projected: ``(neutral (n_points, 2), deltas (n_shapes, n_points, 2), {region: shape
    indices}, landmark JSON path)`` (:func:`~keyshape.retarget.rig.model.rig_landmarks`, ``shape_regions``)."""
    from keyshape.decompose.regions import available_regions, region_points
    from keyshape.retarget.rig.model import project, rig_landmarks, shape_regions

    W, path = rig_landmarks(rig, scheme_name, landmarks)
    deltas = project(np.einsum("pv,svc->spc", W, rig.deltas, optimize=True))
    groups = {r: region_points(scheme, r) for r in available_regions(scheme)}
    return project(W @ rig.neutral), deltas, shape_regions(deltas, groups, names=rig.names), path


def rig_curves(weights: np.ndarray, columns: Sequence[str], library: dict, rig, source=None) -> np.ndarray:
    """The rig's curves (n_frames, n_shapes) for key ``weights`` (n_frames, n_keys) through a pose library."""
    from keyshape.retarget.rig.poses import curves_from_library

    return curves_from_library(weights, columns, library, rig.names, source)


def _head_3d(tracks: Tracks, head, rows: np.ndarray, ref_row: int | None, head_units: float, source):
    """The 3D head's motion of ``rows`` (None where the tracks' scheme has no 3D face)."""
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.decompose.regions import fitted_head_points, head_points, head_pose_3d, model_shapes
    from keyshape.decompose.stabilize import stabilizer_from_entry
    from keyshape.retarget.headpose import head_motion_3d
    try:
        scheme = scheme_for_n_points(tracks.n_points)
    except InputError:
        return None
    from keyshape.decompose.head3d import HeadPose3D
    pose = None
    if isinstance(head, (dict, HeadPose3D)):
        est = stabilizer_from_entry(head)
        pts = fitted_head_points(est, tracks, source)
    else:
        pts, full = head_points(tracks, scheme, source)
        est = head_pose_3d(full, tracks.image_size)
        if est is None:
            return None
        pose = est.fit(pts).camera_pose_                # fitted on these points: its pose solve is theirs
    hp = est.head_pose(pts, pose)
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


def gaze_from_tracks(tracks: Tracks, frames: np.ndarray, head=None, source=None, lid_drag: bool = True,
                     denoise: bool = True) -> np.ndarray:
    """(n_frames, 4) eye angles of the weights' ``frames`` (left yaw, left pitch, right yaw, right pitch,
    radians; :func:`keyshape.decompose.gaze.gaze_angles`) from the pupils in the head's frame (``head``:
    a fitted :class:`~keyshape.decompose.head3d.HeadPose3D`, a :class:`~keyshape.decompose.take.Take`'s ``head3d``,
    a KEYS.json ``head_pose`` entry, or None: fitted here; the 2D rigid head where the scheme has no 3D face), the lids' pull on the pupils during
    blinks taken out (``lid_drag``: :class:`~keyshape.decompose.gaze.LidDrag`, fitted on the take; live, which
    sees no future frame, goes without), and the take's fixations denoised in the world frame (``denoise``:
    :func:`~keyshape.decompose.gaze.denoise_gaze`, the eye angles plus the 3D head's; the head frame where the
    head is 2D; offline only, like ``lid_drag``). Failed frames hold the last good gaze. Raises
    :class:`InputError` when the scheme has no pupils."""
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.decompose.api import take_fps
    from keyshape.decompose.gaze import has_gaze, take_gaze
    from keyshape.decompose.head3d import HeadPose3D
    from keyshape.decompose.regions import fitted_head_points, head_shapes
    scheme = scheme_for_n_points(tracks.n_points)
    shapes, stab = head_shapes(tracks, scheme, "3d" if head is None else head, source)
    ang = None
    if denoise and isinstance(stab, HeadPose3D):        # the pose solve head_shapes made (HeadPose3D keeps it)
        ang = stab.head_pose(fitted_head_points(stab, tracks, source))["angles"]
    g = take_gaze(shapes, scheme, take_fps(tracks), head=ang, lid_drag=lid_drag and has_gaze(scheme),
                  denoise=denoise)
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


def apply_gaze(curves: np.ndarray, rig, tracks: Tracks, frames: np.ndarray, head=HEAD_MOTION, source=None,
               say=print, gaze: str = GAZE) -> tuple[np.ndarray, np.ndarray | None]:
    """The eye angles from the pupils (n_frames, 4; :func:`gaze_from_tracks`; None where the scheme has no
    pupils or ``gaze`` is ``"none"``) and the rig's curves, with ``gaze="shapes"`` its ``eyeLook*`` shapes
    set from them (:func:`~keyshape.retarget.rig.model.gaze_curves`); ``"angles"`` leaves the curves alone. What
    the rig cannot show is said in one line through ``say``.
    """
    from keyshape.retarget.rig.model import gaze_curves
    if gaze not in GAZES:
        raise InputError(f"gaze {gaze!r}: use one of {', '.join(GAZES)}")
    if gaze == "none":
        return curves, None
    try:
        eyes = gaze_from_tracks(tracks, frames, head, source)
    except InputError as exc:
        say(f"keyshape: gaze: {exc}; the eyes keep the curves' gaze")
        return curves, None
    if gaze == "angles":
        say("keyshape: gaze from the pupils -> the Live Link eye angles (the rig's eyeLook* shapes: --gaze shapes)")
        return curves, eyes
    g, cols = gaze_curves(eyes, rig.names)
    if cols:
        curves = curves.copy()
        curves[:, cols] = g[:, cols]
        say(f"keyshape: gaze from the pupils -> {len(cols)} eyeLook* shapes and the Live Link eye angles")
    else:
        say("keyshape: gaze: the rig has no eyeLook* shapes, so its eyes cannot follow the pupils "
            "(the eye angles are in the Live Link eye columns)")
    return curves, eyes


def check_solve_options(sparsity: float, symmetry: float, smooth: float) -> None:
    """One-line :class:`InputError` for a ``solve`` prior out of range (before any work)."""
    for name, v, hi in (("--sparsity", sparsity, 100.0), ("--symmetry", symmetry, 100.0), ("--smooth", smooth, 1e6)):
        if not (np.isfinite(v) and 0.0 <= v <= hi):
            raise InputError(f"{name} {v}: a number from 0 to {hi:g}")


def solve_rig(take: Take, regions, scheme_name: str, head_pose: dict | None, rig,
              options: SolveOptions = SolveOptions(), *, report: dict | None = None):
    """The rig's curves of every frame solved from the tracks (``keyshape solve``, with its defaults).

    Parameters
    ----------
    take : the :class:`~keyshape.decompose.take.Take` (the tracks with their frame rate and fitted 3D head)
    regions, scheme_name, head_pose : the key set's regions (their ``points`` and the actor's neutral, ``rest``),
        scheme and KEYS.json ``head_pose`` entry (how the head is taken out of the shapes)
    rig : a :class:`~keyshape.retarget.rig.model.Rig`
    options : :class:`~keyshape.retarget.defaults.SolveOptions`: the solve's priors and calibrations
        (:class:`~keyshape.retarget.rig.solve.RigSolver`), the gaze (:func:`apply_gaze`), the head motion written
        beside the curves (:func:`head_from_tracks`) and, where the keys' head is 2D and the scheme has a 3D face,
        the mouth's parallax under the 3D head's yaw taken out (:func:`~keyshape.retarget.rig.solve.yaw_slide`,
        :func:`~keyshape.retarget.rig.solve.yaw_stretch`), zero at the mouth's rest frame
    report : a dict that receives what the eye and brow calibrations did
        (:class:`~keyshape.retarget.rig.solve.RigSolver`)

    Returns
    -------
    ``(curves (n_frames, n_shapes), head motion, fps, eye angles or None)``; the frame rate is the take's.
    :func:`fit_solve` gives the solver too.
    """
    solve, motion, rate, eyes = fit_solve(take, regions, scheme_name, head_pose, rig, options, report=report)
    return solve.curves_, motion, rate, eyes


@dataclass
class TakeSolve:
    """:func:`solve_rig`'s solve fitted on a take, and what it needs to read other frames alike (``keyshape live``).

    Attributes
    ----------
    solver : the fitted :class:`~keyshape.retarget.rig.solve.RigSolver`
    scheme, head_pose : the keys' scheme and KEYS.json ``head_pose`` entry (the head-frame shapes of new frames)
    estimator : the take's :class:`~keyshape.decompose.head3d.HeadPose3D` (the yaw and pitch of new frames, each
        posed alone), or None where the solve took no yaw out
    gaze : ``SolveOptions.gaze`` (``shapes``: the eyes' ``eyeLook*`` curves held fixed in the solve)
    rig_names : the rig's shape names
    curves_ : the take's curves (what :func:`solve_rig` returns)
    """

    solver: object
    scheme: object
    head_pose: dict | None
    estimator: object
    gaze: str
    rig_names: list
    curves_: np.ndarray

    def curves(self, tracks: Tracks, eyes: np.ndarray | None = None) -> np.ndarray:
        """The curves (n_frames, n_shapes) of new ``tracks`` (``eyes``: their eye angles (n_frames, 4), for
        ``gaze="shapes"``), solved with the take's statistics
        (:meth:`~keyshape.retarget.rig.solve.RigSolver.transform`)."""
        from keyshape.decompose.regions import fitted_head_points, head_shapes
        from keyshape.retarget.rig.model import gaze_curves

        shapes, _ = head_shapes(tracks, self.scheme, self.head_pose)
        yaw = None
        if self.estimator is not None:
            ang = self.estimator.head_pose(fitted_head_points(self.estimator, tracks))["angles"]
            yaw = ang[:, 0]
            shapes = np.where(np.isfinite(ang[:, :2]).all(axis=1)[:, None, None], shapes, np.nan)
        fixed = None
        if eyes is not None and self.gaze == "shapes":
            fixed, cols = gaze_curves(np.asarray(eyes, float), self.rig_names)
            keep = np.zeros(len(self.rig_names), bool)
            keep[cols] = True
            fixed = np.where(keep[None], fixed, 0.0)
        return self.solver.transform(shapes, yaw, fixed)


def fit_solve(take: Take, regions, scheme_name: str, head_pose: dict | None, rig,
              options: SolveOptions = SolveOptions(), *, report: dict | None = None):
    """:func:`solve_rig`, keeping the fitted solve: ``(TakeSolve, head motion, fps, eye angles or None)``."""
    from keyshape.base.schemes import load_scheme
    from keyshape.decompose.regions import head_shapes
    from keyshape.decompose.stabilize import RigidStabilizer
    from keyshape.retarget.rig.model import gaze_pupil_deltas
    from keyshape.retarget.rig.solve import HeadParallax, RigLandmarks, RigSolver

    o = options
    check_solve_options(o.sparsity, o.symmetry, o.smooth)
    scheme = load_scheme(scheme_name)
    tracks, source, rate = take.tracks, take.source, take.fps
    if tracks.n_points != scheme.n_points:
        raise InputError(f"the tracks have {tracks.n_points} points, the keys' scheme {scheme_name} "
                         f"{scheme.n_points}", source)
    shapes, stab = head_shapes(tracks, scheme, head_pose, source)
    rigid = stab.points if isinstance(stab, RigidStabilizer) else ()   # the frame the rig's motion is read in
    lm_neutral, lm_deltas, reg_shapes, _ = _rig_points(rig, scheme, scheme_name, o.landmarks)
    regs = {rk.region: (rk.points, rk.rest if rk.rest is not None else rk.neutral) for rk in regions}
    units = o.head_units if o.head_units is not None else rig_head_units(rig, tracks, o.landmarks)
    est = take.head3d if o.head == "3d" else None
    kind = est if est is not None else o.head
    motion = head_from_tracks(tracks, tracks.frame, o.reference_frame, units, source, head=kind)
    gazed, eyes = apply_gaze(np.zeros((len(tracks.frame), rig.n_shapes)), rig, tracks, tracks.frame, kind, source,
                             gaze=o.gaze)
    fixed = gazed if eyes is not None and o.gaze == "shapes" else None      # the eyeLook* curves, the rest 0
    yaw, rest_yaw, est = (_solve_yaw(take, regions, head_pose, est) if o.yaw_slide or o.yaw_stretch
                          else (None, 0.0, None))
    lm = RigLandmarks(lm_neutral, gaze_pupil_deltas(lm_neutral, lm_deltas, rig.names, scheme), reg_shapes, rig.names,
                      rig.value_range)
    solver = RigSolver(scheme, lm, o).fit(shapes, regs, HeadParallax(yaw, rest_yaw, rigid), fixed, report)
    return (TakeSolve(solver, scheme, head_pose, est if yaw is not None else None, o.gaze,
                      list(rig.names), solver.curves_), motion, rate, eyes)


def _solve_yaw(take: Take, regions, head_pose: dict | None, est):
    """The 3D head's yaw of every frame and of the mouth's rest frame (its median where the rest frame is not
    one of these tracks'), for :func:`~keyshape.retarget.rig.solve.yaw_slide`, and the fitted head;
    ``(None, 0.0, None)`` where the keys' shapes are frontalised already (``head_pose`` 3d) or the scheme has no
    3D face. ``est``: the take's fitted :class:`~keyshape.decompose.head3d.HeadPose3D` (None: ``take.head3d``)."""
    from keyshape.decompose.regions import fitted_head_points
    none = (None, 0.0, None)
    if (head_pose or {}).get("method") == "3d":
        return none
    tracks, source = take.tracks, take.source
    est = est if est is not None else take.head3d
    if est is None:
        return none
    ang = est.head_pose(fitted_head_points(est, tracks, source), est.camera_pose_)["angles"][:, :2]
    ok = np.isfinite(ang).all(axis=1)
    if not ok.any():
        return none
    t = np.arange(len(ang))
    ang = np.column_stack([np.where(ok, a, np.interp(t, np.flatnonzero(ok), a[ok])) for a in ang.T])
    pos = {int(f): i for i, f in enumerate(tracks.frame)}
    rest = [rk.rest_frame for rk in regions if rk.region == "mouth" and rk.rest_frame is not None and rk.takes is None]
    row = pos.get(int(rest[0])) if rest else None
    at = ang[row] if row is not None else np.median(ang, axis=0)
    return ang[:, 0], float(at[0]), est


def override_poses(curves: np.ndarray, frames: np.ndarray, regions, weights: np.ndarray, columns: Sequence[str],
                   weight_frames: np.ndarray, library: dict, rig, source=None, weights_source=None) -> np.ndarray:
    """The artist's pose library (POSES.json, corrected in ``keyshape pose-edit``) over solved curves, in
    proportion to each frame's key weights (:func:`~keyshape.retarget.rig.solve.pose_override`)."""
    from keyshape.retarget.rig.solve import pose_override

    if len(weight_frames) != len(frames) or (np.asarray(weight_frames) != np.asarray(frames)).any():
        raise InputError("the weights' frames are not the tracks' frames", weights_source)
    key_frames = {k: int(f) for rk in regions for k, f in zip(rk.names, rk.frames)}
    return pose_override(curves, frames, weights, columns, library, rig.names, key_frames, source)
