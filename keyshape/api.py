"""The Python API of the video path: footage in, animation out, objects and arrays in memory.

Files appear only at the edges (the video, a labels folder, the artist's targets, and what
:meth:`Animation.export` writes); everything between is an object::

    from keyshape.api import train, track, select, decompose, retarget

    model = train("footage/video.mp4", "footage/labels")      # labelled frames -> tracker model
    tracks = track("footage/video.mp4", model)                  # Tracks: points, pose, success
    keys = select(tracks, k=8, method="greedy", regions=["mouth", "eyes"])
    weights = decompose(tracks, keys, solver="smooth", ridge=0.03)
    anim = retarget(weights, "targets", regions="targets_regions.json", tracks=tracks)
    anim.export("animation.glb")

The command line (``keyshape train/track/select/decompose/retarget``), ``keyshape demo`` and
``keyshape batch`` run these same steps: each function here calls the stage's in-memory
function (:mod:`keyshape.tracker.commands`, :mod:`keyshape.decompose.api`,
:mod:`keyshape.retarget.api`) that the stage's command calls too, so the stages keep their
floors (a stage never imports this roof module).

``train``, ``track``, ``select`` and the result classes are also reachable as ``keyshape.train``
and so on (loaded on first use); ``decompose`` and ``retarget`` are not, because
``keyshape.decompose`` and ``keyshape.retarget`` are the stage packages: use
``keyshape.api.decompose`` / ``keyshape.api.retarget``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.formats.tracks import Tracks, read_tracks, write_tracks
from keyshape.decompose.regions import RegionKeys
from keyshape.tracker.eigenpoints import AppearanceModel

__all__ = ["train", "track", "select", "decompose", "retarget", "head", "Head", "Keys", "Weights", "Animation", "Tracks",
           "AppearanceModel", "read_tracks", "write_tracks"]


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
    """

    scheme: str
    n_points: int
    regions: list[RegionKeys]
    head_pose: dict | None = None

    @property
    def names(self) -> list[str]:
        """Weight column names ``REGION_K`` in order."""
        return [n for rk in self.regions for n in rk.names]

    def save(self, path: str | Path) -> None:
        """Write KEYS.json atomically."""
        from keyshape.base.formats.keys import write_keys

        write_keys(path, self.scheme, self.n_points, self.regions, head_pose=self.head_pose)

    @classmethod
    def load(cls, path: str | Path) -> "Keys":
        """Read a KEYS.json (errors name the file)."""
        from keyshape.base.formats.keys import read_keys, read_keys_head_pose

        return cls(*read_keys(path), head_pose=read_keys_head_pose(path))


@dataclass
class Weights:
    """Per-frame key-shape weights, what ``keyshape decompose`` writes as WEIGHTS.csv.

    Attributes
    ----------
    frames : (n_frames,) int frame numbers
    names : key-shape columns ``REGION_K``
    values : (n_frames, n_keys) float64
    interpolated : (n_frames,) bool, True where tracking failed and the weights were filled in
    """

    frames: np.ndarray
    names: list[str]
    values: np.ndarray
    interpolated: np.ndarray = field(default=None)

    def __post_init__(self) -> None:
        self.frames = np.asarray(self.frames, dtype=np.int64)
        self.values = np.asarray(self.values, dtype=np.float64)
        if self.interpolated is None:
            self.interpolated = np.zeros(len(self.frames), dtype=bool)
        self.interpolated = np.asarray(self.interpolated, dtype=bool)
        if self.values.shape != (len(self.frames), len(self.names)):
            raise InputError(f"Weights.values: expected shape ({len(self.frames)}, {len(self.names)}), "
                             f"got {self.values.shape}")

    def save(self, path: str | Path) -> None:
        """Write WEIGHTS.csv atomically (``%.6f``, the ``interpolated`` flag last)."""
        from keyshape.base.formats.weights import write_weights

        write_weights(path, self.frames, list(self.names), self.values, self.interpolated)

    @classmethod
    def load(cls, path: str | Path) -> "Weights":
        """Read a WEIGHTS.csv (errors name the file and line)."""
        from keyshape.base.formats.weights import read_weights

        return cls(*read_weights(path))


@dataclass
class Animation:
    """The retargeted performance: a fitted retargeter driven by weights, ready to export.

    Attributes
    ----------
    retargeter : fitted :class:`~keyshape.retarget.retargeter.Retargeter`
    weights : the :class:`Weights` driving it
    fps : frame rate
    head : :class:`~keyshape.retarget.headpose.HeadMotion` from the tracks, or None
    """

    retargeter: object
    weights: Weights
    fps: float = 30.0
    head: object = None

    def vertices(self, chunk_frames: int = 256) -> np.ndarray:
        """The target face per frame: (n_frames, n_vertices, dim)."""
        return self.retargeter.transform(self.weights.values, chunk_frames=chunk_frames)

    def export(self, path: str | Path, clamp: bool = False, livelink: bool = False, bake_head: bool = False,
               scheme=None) -> dict:
        """Write ``path`` atomically: ``.glb``, ``.csv`` (curves, or Live Link with ``livelink``), ``.mp4``,
        or a folder of OBJ/PNG frames; see :func:`keyshape.retarget.export.export`."""
        from keyshape.retarget.export import export

        return export(path, self.retargeter, self.weights.frames, self.weights.values, fps=self.fps,
                      head=self.head, clamp=clamp, livelink=livelink, bake_head=bake_head, scheme=scheme)


def train(video: str | Path, labels, *, scheme: str = "contours48", components: int | None = None,
          morphs: int = 120, seed: int = 0) -> AppearanceModel:
    """Train the person-specific tracking model (``keyshape train``).

    Parameters
    ----------
    video : the footage the labels belong to
    labels : a folder of ``NNNNNN.pts`` files, or ``(frames (n,), shapes (n, n_points, 2))`` arrays
    scheme : landmark scheme; components : eigenvectors kept (None: 98% of the variance);
    morphs : morphed training images added; seed : seed of the morph pairs

    Returns
    -------
    fitted :class:`~keyshape.tracker.eigenpoints.AppearanceModel` (``.save(path)`` writes it)
    """
    from keyshape.tracker.commands import fit_model

    return fit_model(video, labels, scheme, n_components=components, n_morphs=morphs, rng=seed)


def track(video: str | Path, model, *, smooth: str = "none", start: int = 0, stop: int | None = None,
          progress: bool = False) -> Tracks:
    """Track frames ``start``..``stop`` (exclusive) of ``video`` (``keyshape track``).

    ``model`` is a fitted model or a model file; ``smooth`` is ``none``, ``savgol`` or ``oneeuro``.
    Returns :class:`~keyshape.base.formats.tracks.Tracks` (lost frames have ``success`` False).
    """
    from keyshape.tracker.commands import track_frames

    return track_frames(video, model, smooth=smooth, start=start, stop=stop, show_progress=progress)


def select(tracks: Tracks | Sequence[Tracks], k: int | None, method: str = "spread",
           regions: Sequence[str] | None = None, *, scheme: str | None = None, seed: int = 0,
           head: str = "3d") -> Keys:
    """Choose ``k`` key shapes per region (``keyshape select``).

    ``tracks`` may be a list (several takes of one actor, one key set for all): they are
    concatenated in order and the keys' ``frames`` count frames across that concatenation.
    ``method``: spread (the paper's), kmeans2, kmeans3, hull2, random, greedy. ``head``: ``3d`` (the
    head's 3D pose removed, the shapes brought to the front; the default), ``rigid`` (a 2D similarity on
    the scheme's rigid points) or ``tracker`` (its pose alone).
    """
    from keyshape.decompose.api import concat_tracks, select_keys

    if not isinstance(tracks, Tracks):
        tracks = concat_tracks(tracks)
    sch, chosen, head_pose = select_keys(tracks, k, method, regions, scheme, seed, head=head)
    return Keys(sch.name, sch.n_points, chosen, head_pose)


def decompose(tracks: Tracks, keys: Keys, solver: str = "nnls", ridge: float = 0.0,
              smooth_lambda: float = 0.1) -> Weights:
    """Per-frame weights of ``keys`` for every frame of ``tracks`` (``keyshape decompose``).

    ``solver``: nnls (eq. 4), lstsq or smooth; ``ridge`` shrinks weights against tracking noise.
    Failed frames are interpolated and flagged in :attr:`Weights.interpolated`.
    """
    from keyshape.decompose.api import decompose_keys

    if keys.n_points != tracks.n_points:
        raise InputError(f"key shapes are for {keys.n_points} points ({keys.scheme}), the tracks have "
                         f"{tracks.n_points}")
    names, w = decompose_keys(tracks, keys.regions, solver, smooth_lambda, ridge, head_pose=keys.head_pose)
    return Weights(tracks.frame, names, w, ~tracks.success)


def retarget(weights: Weights, targets, regions=None, *, tracks: Tracks | None = None, neutral=None, mapping=None,
             form: str = "auto", band: float | None = None, metric: str = "geodesic", fps: float | None = None,
             reference_frame: int | None = None, head_units: float = 1.0, head: str = "3d") -> Animation:
    """Drive the artist's target key shapes with ``weights`` (``keyshape retarget``).

    Parameters
    ----------
    targets : a folder or list of target files (OBJ meshes or 2D drawings) named by the weight
        columns, or a :class:`~keyshape.retarget.targets.TargetSet`
    regions : ``{region: vertex indices}``, a regions JSON or a grouped OBJ (None: no regions)
    tracks : give the head motion (root transform) and the frame rate
    neutral, mapping, form, band, metric : as ``keyshape retarget``
    fps : frame rate (default: from the tracks, else 30)
    reference_frame, head : the head's rest frame and kind (``3d``, ``rigid``, ``tracker``), as
        ``keyshape retarget --reference-frame/--head-pose``
    """
    from keyshape.retarget.api import fit_retargeter, head_from_tracks

    rt = fit_retargeter(weights.names, targets, regions, mapping=mapping, neutral=neutral, form=form, band=band,
                        metric=metric)
    if tracks is not None:
        motion, tracks_fps = head_from_tracks(tracks, weights.frames, reference_frame, head_units, head=head)
        fps = fps or tracks_fps
        return Animation(rt, weights, float(fps or 30.0), motion)
    return Animation(rt, weights, float(fps or 30.0), None)


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
    from keyshape.decompose.gaze import gaze_angles, has_gaze
    from keyshape.decompose.regions import head_pose_3d, image_points

    scheme = scheme_for_n_points(tracks.n_points)
    est = head_pose_3d(scheme)
    if est is None:
        raise InputError(f"scheme {scheme.name!r} has no 3D face or no rigid points: no 3D head pose")
    pts = image_points(tracks)
    est.fit(pts)
    hp = est.head_pose(pts)
    gaze = np.degrees(gaze_angles(est.transform(pts), scheme)) if has_gaze(scheme) else None
    return Head(tracks.frame.copy(), np.degrees(hp["angles"]), hp["translation"], hp["rotation"], gaze, est)
