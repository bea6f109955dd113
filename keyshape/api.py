"""The Python API of the video path: footage in, animation out, objects and arrays in memory.

Design notes and figures: docs/python.md, "Notes on the code", ``keyshape/api.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.formats.tracks import Tracks, read_tracks, write_tracks
from keyshape.decompose import api as D
from keyshape.retarget import api as RA
from keyshape.retarget.defaults import PreviewOptions, RetargetOptions, SolveOptions
from keyshape.decompose.regions import RegionKeys
from keyshape.tracker.eigenpoints import AppearanceModel

__all__ = ["train", "track", "select", "decompose", "retarget", "solve", "SolveOptions", "RetargetOptions", "PreviewOptions", "pose", "preview", "load_rig",
           "head", "Head", "Keys", "Weights", "Animation", "RigAnimation", "PoseLibrary", "Tracks", "AppearanceModel", "read_tracks",
           "write_tracks"]


@dataclass
class Keys:
    """Key shapes of one or more regions (model frame), what ``keyshape select`` writes as KEYS.json.

    Attributes
    ----------
    scheme : landmark scheme name; n_points : its point count
    regions : one :class:`~keyshape.decompose.regions.RegionKeys` per region; their ``frames`` are
        the tracks' frame numbers (for a key set chosen over several takes, positions in the takes
        concatenated in the order given, see :func:`select`)
    head_pose : how the head was taken out of the shapes (KEYS.json's ``head_pose``; None: the
        tracker's pose alone), applied again by :func:`decompose`
    source : where the keys came from (KEYS.json's ``source``): ``{"model": "sha256:...", "scheme": ...}``
        when the tracks carried their model's fingerprint; :func:`decompose` refuses keys of another
        model's tracks unless told otherwise
    """

    scheme: str
    n_points: int
    regions: list[RegionKeys]
    head_pose: dict | None = None
    source: dict | None = None

    @property
    def names(self) -> list[str]:
        """Weight column names ``REGION_K`` in order."""
        return [n for rk in self.regions for n in rk.names]

    def save(self, path: str | Path) -> None:
        """Write KEYS.json atomically."""
        from keyshape.base.formats.keys import write_keys

        write_keys(path, self.scheme, self.n_points, self.regions, source=self.source, head_pose=self.head_pose)

    @classmethod
    def load(cls, path: str | Path) -> "Keys":
        """Read a KEYS.json (errors name the file)."""
        from keyshape.base.formats.keys import read_keys, read_keys_head_pose, read_keys_source

        return cls(*read_keys(path), head_pose=read_keys_head_pose(path), source=read_keys_source(path) or None)


@dataclass
class Weights:
    """Per-frame key-shape weights, what ``keyshape decompose`` writes as WEIGHTS.csv.

    Attributes
    ----------
    frames : (n_frames,) int frame numbers
    names : key-shape columns ``REGION_K``
    values : (n_frames, n_keys) float64
    interpolated : (n_frames,) bool, True where tracking failed and the weights were filled in
    fps : the take's frame rate (from the tracks' timestamps; None where unknown), written to and
        read from WEIGHTS.csv's leading comment, so a retarget without the tracks keeps the take's rate
    """

    frames: np.ndarray
    names: list[str]
    values: np.ndarray
    interpolated: np.ndarray = field(default=None)
    fps: float | None = None

    def __post_init__(self) -> None:
        fr = np.asarray(self.frames)
        if fr.dtype.kind not in "biuf" or fr.ndim != 1 or (fr.dtype.kind == "f" and not (
                np.isfinite(fr).all() and (fr == np.round(fr)).all())):
            raise InputError(f"Weights.frames must be whole frame numbers, got {fr[:5].tolist()}")
        self.frames = fr.astype(np.int64)
        self.values = np.asarray(self.values, dtype=np.float64)
        if self.interpolated is None:
            self.interpolated = np.zeros(len(self.frames), dtype=bool)
        self.interpolated = np.asarray(self.interpolated, dtype=bool)
        if self.values.shape != (len(self.frames), len(self.names)):
            raise InputError(f"Weights.values: expected shape ({len(self.frames)}, {len(self.names)}), "
                             f"got {self.values.shape}")

    def save(self, path: str | Path) -> None:
        """Write WEIGHTS.csv atomically (``%.6f``, the ``time`` column where ``fps`` is known, the ``interpolated`` flag last)."""
        from keyshape.base.formats.weights import write_weights

        write_weights(path, self.frames, list(self.names), self.values, self.interpolated, fps=self.fps)

    @classmethod
    def load(cls, path: str | Path) -> "Weights":
        """Read a WEIGHTS.csv (errors name the file and line)."""
        from keyshape.base.formats.weights import read_weights, read_weights_fps

        return cls(*read_weights(path), fps=read_weights_fps(path))


@dataclass
class Animation:
    """The retargeted performance: a fitted retargeter driven by weights, ready to export.

    Attributes
    ----------
    retargeter : fitted :class:`~keyshape.retarget.targets.retargeter.Retargeter`
    weights : the :class:`Weights` driving it
    fps : frame rate
    head : :class:`~keyshape.retarget.headpose.HeadMotion` from the tracks, or None
    """

    retargeter: object
    weights: Weights
    fps: float = RA.DEFAULT_FPS
    head: object = None
    eyes: np.ndarray | None = None

    def vertices(self, chunk_frames: int = 256) -> np.ndarray:
        """The target face per frame: (n_frames, n_vertices, dim)."""
        return self.retargeter.transform(self.weights.values, chunk_frames=chunk_frames)

    def export(self, path: str | Path, clamp: bool = False, livelink: bool = False, bake_head: bool = False,
               scheme=None, meters_per_unit: float = 0.01) -> dict:
        """Write ``path`` atomically: ``.glb``, ``.usda``/``.usdc``/``.usd`` (``keyshape[usd]``; ``meters_per_unit``:
        the meshes' unit, default centimetres), ``.csv`` (curves, or Live Link with ``livelink``), ``.mp4``,
        or a folder of OBJ/PNG frames; see :func:`keyshape.retarget.output.export.export`."""
        from keyshape.retarget.output.export import ExportOptions, export

        return export(path, self.retargeter, self.weights.frames, self.weights.values, fps=self.fps,
                      head=self.head, options=ExportOptions(clamp=clamp, livelink=livelink, bake_head=bake_head,
                                                            scheme=scheme, meters_per_unit=meters_per_unit))


def _what(obj) -> str:
    return f"the path {str(obj)!r}" if isinstance(obj, (str, Path)) else f"{type(obj).__name__}"


def _expect(obj, types, name: str, what: str) -> None:
    """One-line :class:`InputError` when an argument is not of the expected kind (e.g. a path where
    an object is expected, or None)."""
    if isinstance(obj, bool) or not isinstance(obj, types):
        raise InputError(f"{name}: expected {what}, got {_what(obj)}")


def train(video: str | Path, labels, *, scheme: str | None = None, components: int | None = None,
          morphs: int = 120, seed: int = 0) -> AppearanceModel:
    """Train the person-specific tracking model (``keyshape train``).

    Parameters
    ----------
    video : the footage the labels belong to
    labels : a folder of ``NNNNNN.pts`` files, or ``(frames (n,), shapes (n, n_points, 2))`` arrays
    scheme : landmark scheme (None: the one the labels folder was made in, else contours48); components : eigenvectors kept (None: 98% of the variance);
    morphs : morphed training images added; seed : seed of the morph pairs

    Returns
    -------
    fitted :class:`~keyshape.tracker.eigenpoints.AppearanceModel` (``.save(path)`` writes it)
    """
    from keyshape.tracker.commands import fit_model

    return fit_model(video, labels, scheme, n_components=components, n_morphs=morphs, rng=seed)


def track(video: str | Path, model, *, smooth: str = "none", start: int = 0, stop: int | None = None,
          progress: bool = False, decode_thread: bool = True, jobs: int | None = 1) -> Tracks:
    """Track frames ``start``..``stop`` (exclusive) of ``video`` (``keyshape track``).

    ``model`` is a fitted model or a model file; ``smooth`` is ``none``, ``savgol`` or ``oneeuro``.
    ``decode_thread`` False decodes on the tracking thread (one core per call, as a batch worker is).
    ``jobs``: worker processes tracking contiguous chunks of the range, stitched in frame order (the
    same points within the tracker's convergence tolerance; None: one per core, at least 500 frames
    each, as ``keyshape track`` does by default); 1 (default) tracks in this process.
    Returns :class:`~keyshape.base.formats.tracks.Tracks` (lost frames have ``success`` False).
    """
    from keyshape.tracker.commands import track_frames
    from keyshape.tracker.defaults import TrackOptions

    _expect(model, (AppearanceModel, str, Path), "model", "a fitted AppearanceModel or a model file")
    _expect(video, (str, Path), "video", "a video file path")
    return track_frames(video, model, TrackOptions(smooth, start, stop, jobs, decode_thread), show_progress=progress)


def select(tracks: Tracks | Sequence[Tracks], k: int | None, method: str = D.METHOD,
           regions: Sequence[str] | None = None, *, scheme: str | None = None, seed: int = D.SEED,
           head: str = D.HEAD_POSE, neutral_frame: int | str | None = D.NEUTRAL_FRAME, progress: bool = False) -> Keys:
    """Choose ``k`` key shapes per region (``keyshape select``, with its defaults).

    ``tracks`` may be a list (several takes of one actor, one key set for all): the keys' ``frames``
    are then each take's frame numbers and their ``takes`` which take, as ``keyshape select`` with
    several files writes them. ``method``: greedy (default), spread (the paper's), kmeans2, kmeans3,
    hull2, random. ``head``: ``3d`` (the head's 3D pose removed, the shapes brought to the front), ``rigid``
    (a 2D similarity on the scheme's rigid points) or ``tracker`` (its pose alone); default as the command's. ``neutral_frame``: ``"auto"`` (weights relative to the actor's
    most relaxed frame, the default), a frame number, or ``"mean"`` (the take's mean, the paper's
    centring). Near-duplicate keys are dropped (:data:`keyshape.decompose.defaults.MIN_KEY_DISTANCE`). See
    :func:`keyshape.decompose.api.select_keys`.
    """
    takes = [tracks] if isinstance(tracks, Tracks) else tracks
    if isinstance(takes, (str, Path, bytes)) or not isinstance(takes, Sequence) or not takes or \
            not all(isinstance(t, Tracks) for t in takes):
        raise InputError(f"select: tracks must be Tracks or a list of Tracks (read a file with read_tracks), "
                         f"got {_what(tracks)}")
    if isinstance(regions, str):
        regions = [regions]
    models = {t.meta.get("model") for t in takes}
    sch, chosen, head_pose = D.select_keys(takes[0] if len(takes) == 1 else list(takes), k, method, regions, scheme,
                                           seed, progress=progress, head=head, neutral_frame=neutral_frame)
    model = models.pop() if len(models) == 1 else None
    source = {"model": model, "scheme": sch.name} if model else None
    return Keys(sch.name, sch.n_points, chosen, head_pose, source)


def decompose(tracks: Tracks, keys: Keys, solver: str = D.SOLVER, ridge: float = D.RIDGE,
              smooth_lambda: float = D.SMOOTH_LAMBDA, *, allow_foreign_keys: bool = False) -> Weights:
    """Per-frame weights of ``keys`` for every frame of ``tracks`` (``keyshape decompose``, with its defaults).

    ``solver``: smooth (NNLS + temporal smoothness, the default), nnls (eq. 4) or lstsq; ``ridge``
    (default 0.03) shrinks weights against tracking noise. Failed frames are interpolated and flagged
    in :attr:`Weights.interpolated`.
    """
    _expect(tracks, Tracks, "tracks", "Tracks (read a file with read_tracks)")
    _expect(keys, Keys, "keys", "Keys (read a file with Keys.load)")
    mk, mt = (keys.source or {}).get("model"), tracks.meta.get("model")
    if mk and mt and mk != mt and not allow_foreign_keys:
        raise InputError(f"these keys were chosen from tracks of another tracker model ({mk}; these tracks: {mt}): "
                         "select keys from this model's tracks, or pass allow_foreign_keys=True")
    if keys.n_points != tracks.n_points:
        raise InputError(f"key shapes are for {keys.n_points} points ({keys.scheme}), the tracks have "
                         f"{tracks.n_points}")
    names, w = D.decompose_keys(tracks, keys.regions, solver, smooth_lambda, ridge, head_pose=keys.head_pose)
    return Weights(tracks.frame, names, w, ~tracks.success, tracks.fps)


def load_rig(rig, neutral=None, with_mesh: bool = True):
    """A blendshape rig (:class:`~keyshape.retarget.rig.model.Rig`) from a folder or a list of OBJ files, as the
    commands' ``--rig`` (``neutral``: their ``--neutral``); parsed once, then read from the rig cache."""
    from keyshape.retarget.rig.model import Rig, load_rig as _load

    return rig if isinstance(rig, Rig) else _load(rig, neutral, with_mesh=with_mesh)


@dataclass
class PoseLibrary:
    """Every key's pose on a rig (``keyshape pose``), what POSES.json holds.

    Attributes
    ----------
    data : POSES.json's layout (``keys``, ``rig``, ``range``, ``regions``: per region its ``shapes``,
        ``neutral`` pose and per key ``{rig shape: weight}``)
    residuals : per key the share of its landmark motion the pose does not reproduce (None when read
        from a file)
    """

    data: dict
    residuals: dict | None = None

    def save(self, path: str | Path) -> None:
        """Write POSES.json atomically."""
        from keyshape.base.formats.poses import write_poses

        write_poses(path, self.data)

    @classmethod
    def load(cls, path: str | Path, rig=None) -> "PoseLibrary":
        """Read a POSES.json (checked against ``rig``'s shape names when given)."""
        from keyshape.base.formats.poses import read_poses

        return cls(read_poses(path, None if rig is None else list(rig.names)))


def pose(keys: Keys, rig, *, neutral=None, landmarks=None, sparsity: float = RA.SPARSITY,
         nuisance: str = RA.NUISANCE, opposed: float = RA.OPPOSED, symmetry: float = RA.SYMMETRY) -> PoseLibrary:
    """Suggest every key's pose on an artist's blendshape rig (``keyshape pose``, with its defaults).

    ``rig``: a :class:`~keyshape.retarget.rig.model.Rig` (:func:`load_rig`) or its folder / OBJ files
    (``neutral``: its neutral OBJ). ``landmarks``: rig landmark JSON (default: the shipped one for
    ICT-FaceKit rigs). See :func:`keyshape.retarget.api.fit_poses`.
    """
    r = load_rig(rig, neutral, with_mesh=False)
    data, fit = RA.fit_poses(keys.regions, keys.scheme, r, keys.head_pose, landmarks, sparsity, nuisance, opposed,
                             symmetry)
    return PoseLibrary({"keys": {"scheme": keys.scheme}, **data}, fit)


@dataclass
class RigAnimation:
    """A rig driven by its own curves (``keyshape retarget --poses --rig``), ready to export.

    Attributes
    ----------
    rig : the :class:`~keyshape.retarget.rig.model.Rig`
    frames : (n_frames,) frame numbers
    curves : (n_frames, n_shapes) the rig shapes' weights
    fps : frame rate
    head : :class:`~keyshape.retarget.headpose.HeadMotion` in the rig's units, or None
    eyes : (n_frames, 4) eye angles from the pupils (left yaw, pitch, right yaw, pitch; radians), or None
    calibration : what :func:`solve`'s calibrations did (``"eyes"``: one
        :class:`~keyshape.retarget.rig.solve.EyeCalibration` per eye, ``"brows"``: {shape: scale}), or None
    """

    rig: object
    frames: np.ndarray
    curves: np.ndarray
    fps: float = RA.DEFAULT_FPS
    head: object = None
    eyes: np.ndarray | None = None
    calibration: dict | None = None

    def vertices(self) -> np.ndarray:
        """The rig per frame: (n_frames, n_vertices, 3)."""
        return self.rig.evaluate(self.curves)

    def export(self, path: str | Path, livelink: bool = False) -> dict:
        """Write ``path`` atomically: ``.csv`` (the rig's curves, or Live Link with ``livelink``), ``.glb``,
        ``.mp4`` (the shaded rig) or a folder of OBJ frames; see :func:`keyshape.retarget.output.rig_export.export_rig`."""
        from keyshape.retarget.output.rig_export import export_rig

        if not str(path).lower().endswith(".csv") and self.rig.mesh is None:
            self.rig = load_rig(self.rig.files if len(self.rig.files) else self.rig.neutral_file,
                                self.rig.neutral_file)
        return export_rig(path, self.rig, self.frames, self.curves, fps=self.fps, head=self.head, livelink=livelink,
                          eyes=self.eyes)


def solve(tracks: Tracks, keys: Keys, rig, options: SolveOptions | None = None, *, neutral=None,
          poses: "PoseLibrary | str | Path | None" = None, weights: Weights | None = None) -> RigAnimation:
    """Drive a rig by solving its curves of every frame from ``tracks`` (``keyshape solve``, with its defaults).

    ``keys`` gives the head stabilisation, the regions and the actor's neutral; ``rig`` a
    :class:`~keyshape.retarget.rig.model.Rig` or its folder / OBJ files (``neutral``: its neutral OBJ). ``options``: a
    :class:`SolveOptions` (None: the command's defaults): the priors, the calibrations, the gaze, the rig's
    landmarks and the head written beside the curves (:func:`keyshape.retarget.api.solve_rig`).
    ``poses`` (a corrected pose library) with the take's key ``weights``: the artist's poses over the solve,
    as ``keyshape solve --poses --weights``.
    """
    _expect(tracks, Tracks, "tracks", "Tracks (read a file with read_tracks)")
    _expect(keys, Keys, "keys", "Keys (read a file with Keys.load)")
    r = load_rig(rig, neutral, with_mesh=False)
    report: dict = {}
    curves, motion, rate, eyes = RA.solve_rig(D.Take.fit(tracks), keys.regions, keys.scheme, keys.head_pose, r,
                                              options or SolveOptions(), report=report)
    if (poses is None) != (weights is None):
        raise InputError("solve: poses and weights go together (the artist's pose library and the key weights)")
    if poses is not None:
        _expect(weights, Weights, "weights", "Weights (read a file with Weights.load)")
        lib = poses if isinstance(poses, PoseLibrary) else PoseLibrary.load(poses, r)
        curves = RA.override_poses(curves, tracks.frame, keys.regions, weights.values, weights.names, weights.frames,
                                   lib.data, r, None if isinstance(poses, PoseLibrary) else poses)
    return RigAnimation(r, tracks.frame.copy(), curves, rate, motion, eyes, report)


def retarget(weights: Weights, targets=None, regions=None, options: RetargetOptions | None = None, *,
             poses: PoseLibrary | str | Path | None = None, rig=None, tracks: Tracks | None = None, neutral=None,
             mapping=None):
    """Drive the artist's target key shapes, or a rig through a pose library, with ``weights``
    (``keyshape retarget``, with its defaults).

    Parameters
    ----------
    targets : a folder or list of target files (OBJ meshes or 2D drawings) named by the weight
        columns, or a :class:`~keyshape.retarget.targets.target_set.TargetSet` (the paper's route)
    regions : ``{region: vertex indices}``, a regions JSON or a grouped OBJ, or ``"auto"`` (None: no regions)
    options : a :class:`RetargetOptions` (None: the command's defaults): the blend's form, band and metric, the
        gaze, the head written with ``tracks`` and the rig's landmarks
    poses, rig : instead of targets, a pose library (:func:`pose`, or a POSES.json) and the rig it is for
        (a :class:`~keyshape.retarget.rig.model.Rig` or its folder; ``neutral``: the rig's neutral OBJ)
    tracks : give the head motion (root transform), with a rig the pupils' gaze, and the frame rate (else the
        weights' own, else 30)
    neutral, mapping : as ``keyshape retarget --neutral/--map``

    Returns
    -------
    :class:`Animation` (targets) or :class:`RigAnimation` (rig)
    """
    o = options or RetargetOptions()
    _expect(weights, Weights, "weights", "Weights (read a file with Weights.load)")
    if len(weights.frames) == 0:
        raise InputError("retarget: the weights have no frames")
    if tracks is not None:
        _expect(tracks, Tracks, "tracks", "Tracks (read a file with read_tracks)")
    if poses is not None or rig is not None:
        if poses is None or rig is None:
            raise InputError("poses and rig go together (drive a rig with a pose library)")
        if targets is not None:
            raise InputError("targets is for one sculpted target per key; with poses give the rig only")
        r = load_rig(rig, neutral, with_mesh=False)
        lib = poses if isinstance(poses, PoseLibrary) else PoseLibrary.load(poses, r)
        curves = RA.rig_curves(weights.values, weights.names, lib.data, r,
                               None if isinstance(poses, PoseLibrary) else poses)
        motion, fps, kind = RA.take_motion(tracks, weights.frames, weights.fps, r, o)
        eyes = None
        if tracks is not None:
            curves, eyes = RA.apply_gaze(curves, r, tracks, weights.frames, kind, gaze=o.gaze)
        return RigAnimation(r, weights.frames, curves, fps, motion, eyes)
    if targets is None:
        raise InputError("give targets (one target per key) or poses and a rig")
    rt = RA.fit_retargeter(weights.names, targets, regions, mapping=mapping, neutral=neutral, form=o.form, band=o.band,
                           metric=o.metric)
    motion, fps, _ = RA.take_motion(tracks, weights.frames, weights.fps, None, o)
    return Animation(rt, weights, fps, motion)


def preview(video: str | Path, tracks: Tracks, animation: RigAnimation, path: str | Path | None = None, *,
            sheet: str | Path | None = None, options: PreviewOptions | None = None) -> dict:
    """The take's footage with its contours beside the shaded rig (``keyshape preview``): write ``path``
    (.mp4/.avi) and/or ``sheet`` (.jpg/.png); ``options`` (:class:`~keyshape.retarget.defaults.PreviewOptions`):
    the range ``frames`` ``"A:B"``, the ``size``, the sheet's frames, the drawing threads."""
    from keyshape.retarget.output.preview_cli import write_preview

    r = animation.rig
    if r.mesh is None:
        r = animation.rig = load_rig(r.files, r.neutral_file)
    from keyshape.retarget.headpose import head_rotations_of

    return write_preview(video, tracks, r, animation.frames, animation.curves, path, sheet=sheet,
                         head=head_rotations_of(animation.head), options=options)



@dataclass
class Head:
    """The head's 3D pose and the eyes' gaze per frame of a track (:func:`head`).

    Attributes
    ----------
    frames : (n_frames,) frame numbers
    angles : (n_frames, 3) yaw, pitch, roll in degrees (yaw > 0: the actor turns to their left; pitch > 0:
        looks down; roll > 0: tilts toward their right shoulder), 0 at the actor's most front-facing
        relaxed frame; NaN where tracking failed
    translation : (n_frames, 3) cm from that frame, head axes (x the actor's left, y up, z toward the camera)
    rotation : (n_frames, 3, 3) head rotations in head axes
    gaze : (n_frames, 4) left yaw, left pitch, right yaw, right pitch in degrees, or None (no pupils)
    estimator : the fitted :class:`~keyshape.decompose.head3d.HeadPose3D` (its ``to_dict`` is KEYS.json's
        ``head_pose``)
    """

    frames: np.ndarray
    angles: np.ndarray
    translation: np.ndarray
    rotation: np.ndarray
    gaze: np.ndarray | None
    estimator: object


def head(tracks: Tracks) -> Head:
    """The head's 3D pose and gaze of every frame of ``tracks`` (what ``keyshape retarget --tracks``
    writes to the Live Link CSV, the curves CSV's head columns and the .glb head node)."""
    from keyshape.base.errors import InputError
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.decompose.gaze import has_gaze, take_gaze
    from keyshape.decompose.regions import head_points, head_pose_3d

    scheme = scheme_for_n_points(tracks.n_points)
    pts, full = head_points(tracks, scheme)
    est = head_pose_3d(full, tracks.image_size)
    if est is None:
        raise InputError(f"scheme {scheme.name!r} has no 3D face or no rigid points: no 3D head pose")
    est.fit(pts)
    hp = est.head_pose(pts)
    gaze = None
    if has_gaze(scheme):                                # the same chain as retarget's gaze_from_tracks
        shapes = est.transform(pts)[:, :tracks.n_points]
        gaze = np.degrees(take_gaze(shapes, scheme, D.take_fps(tracks), head=hp["angles"]))
    return Head(tracks.frame.copy(), np.degrees(hp["angles"]), hp["translation"], hp["rotation"], gaze, est)
