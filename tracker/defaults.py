"""The tracker stage's options, in one place: a leaf module (no stage imports)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TrackOptions:
    """How a video is tracked (:func:`~keyshape.tracker.commands.iter_track`, ``track_frames``, ``track_video``,
    :func:`~keyshape.tracker.chunked.iter_track_chunked`).

    Attributes
    ----------
    smooth : temporal smoothing of the points: ``none``, ``savgol`` or ``oneeuro`` (delays the output by its window)
    start, stop : the frames tracked, ``stop`` exclusive (None: to the end); frames before ``start`` are decoded
        and skipped, the tracker starts afresh at ``start``
    jobs : worker processes tracking contiguous chunks of the range, stitched in frame order (1: this process;
        None: :func:`~keyshape.tracker.commands.auto_jobs`, for ``track_frames`` and ``track_video``)
    decode_thread : decode (and convert to gray) on a thread of its own, ahead of the tracker (False: on the
        tracking thread, one core, as a batch worker does)
    tracker : keyword options of :class:`~keyshape.tracker.fitting.Tracker` (None: its defaults)
    """

    smooth: str = "none"
    start: int = 0
    stop: int | None = None
    jobs: int | None = 1
    decode_thread: bool = True
    tracker: dict | None = None
