"""The take, fitted once: what every stage after tracking reads of a tracked performance.

Design notes and figures: docs/decompose.md, "Notes on the code", ``decompose/take.py``.
"""
from __future__ import annotations

from dataclasses import dataclass

from keyshape.base.errors import InputError
from keyshape.base.formats.tracks import Tracks
from keyshape.base.schemes import Scheme, scheme_for_n_points
from keyshape.decompose.defaults import DEFAULT_FPS
from keyshape.decompose.head3d import HeadPose3D


def take_fps(tracks: Tracks | None = None, fallback: float | None = None) -> float:
    """The take's frame rate, the one rule every stage uses: the tracks' (:attr:`Tracks.fps`, what the tracker
    recorded of the video), else ``fallback`` (a WEIGHTS.csv's), else :data:`~keyshape.decompose.defaults.DEFAULT_FPS`."""
    return float((tracks.fps if tracks is not None else None) or fallback or DEFAULT_FPS)


@dataclass(eq=False)
class Take:
    """A tracked take and what is fitted to it once (build it with :meth:`fit`).

    Attributes
    ----------
    tracks : the take's :class:`~keyshape.base.formats.tracks.Tracks` (frames, times, points, the tracker's pose)
    scheme : its landmark scheme (None for a point count no built-in scheme has)
    fps : the video's frame rate (:func:`take_fps`)
    head3d : the 3D head fitted to the take (:class:`~keyshape.decompose.head3d.HeadPose3D`), or None where the
        scheme has no 3D face or no frame was tracked
    source : the tracks file, named in errors
    """

    tracks: Tracks
    scheme: Scheme | None
    fps: float
    head3d: HeadPose3D | None
    source: object = None

    @classmethod
    def fit(cls, tracks: Tracks, source=None) -> "Take":
        """The take of ``tracks``: its scheme, frame rate and fitted 3D head."""
        from keyshape.decompose.regions import head_points, head_pose_3d
        try:
            scheme = scheme_for_n_points(tracks.n_points)
        except InputError:                    # no built-in scheme: the tracker's pose alone, no 3D head
            scheme = None
        head = None
        if scheme is not None and tracks.success.any():
            pts, full = head_points(tracks, scheme, source)
            est = head_pose_3d(full, tracks.image_size)
            head = None if est is None else est.fit(pts)
        return cls(tracks, scheme, take_fps(tracks), head, source)

    @property
    def frame(self):
        """The take's frame numbers (n_frames,)."""
        return self.tracks.frame
