"""File-level drivers of ``keyshape train`` and ``keyshape track`` (video and label files in, files out).

The algorithms (:mod:`keyshape.tracker.eigenpoints`, :mod:`keyshape.tracker.fitting`) never open
files; this module does, streaming the video so that memory does not grow
with its length, writing every output atomically, and keeping what was
tracked when the video is truncated or the run is interrupted (Ctrl-C).
"""
from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.files import atomic_write
from keyshape.base.progress import Progress
from keyshape.tracker.eigenpoints import AppearanceModel
from keyshape.base.formats.tracks import TracksWriter, read_labels
from keyshape.base.schemes import load_scheme
from keyshape.base.formats.video import VideoReader, video_info


def train_model(video, labels_dir, scheme="contours48", n_components: int | None = None, n_morphs: int = 120,
                rng=0, **model_options) -> tuple[AppearanceModel, float]:
    """Read the labelled frames of ``video`` and fit an :class:`AppearanceModel`; return it and the seconds taken."""
    t0 = time.perf_counter()
    sch = load_scheme(scheme)
    frames, shapes = read_labels(labels_dir, n_points=sch.n_points)
    info = video_info(video)
    if info.n_frames > 0 and frames.max() >= info.n_frames:
        bad = [int(f) for f in frames if f >= info.n_frames]
        raise InputError(f"labels for frames {bad[:5]} but the video has {info.n_frames} frames "
                         f"(frames are numbered from 0)", Path(labels_dir))
    images = VideoReader(video, gray=True).read_frames(frames)
    h, w = images.shape[1:3]
    outside = (shapes[..., 0] < -0.5 * w) | (shapes[..., 0] > 1.5 * w) | (shapes[..., 1] < -0.5 * h) | \
              (shapes[..., 1] > 1.5 * h)
    if outside.any():
        f = int(frames[np.flatnonzero(outside.any(1))[0]])
        raise InputError(f"points far outside the {w}x{h} frame: are these labels for this video?",
                         Path(labels_dir) / f"{f:06d}.pts")
    model = AppearanceModel(sch, n_components=n_components, n_morphs=n_morphs, rng=rng,
                            **model_options).fit(list(images), shapes)
    return model, time.perf_counter() - t0


@dataclass
class TrackSummary:
    n_frames: int
    expected: int
    n_lost: int
    fps: float
    truncated: bool
    interrupted: bool
    message: str


def track_video(video, model, output, overlay=None, smooth: str = "none", show_progress: bool = True,
                tracker_options: dict | None = None, scheme=None) -> TrackSummary:
    """Track ``video`` with ``model`` (an AppearanceModel or a model file) into a tracks CSV at ``output``.

    Frames are decoded, tracked, written and (with ``overlay``) drawn one at a
    time. A truncated video yields the frames that decoded; Ctrl-C stops the
    loop and keeps the rows written so far (the summary says which).
    """
    import cv2

    from keyshape.base.draw import draw_shape
    from keyshape.tracker.fitting import Tracker
    from keyshape.tracker.smoothing import StreamSmoother
    from keyshape.base.formats.video import video_writer

    if not isinstance(model, AppearanceModel):
        model = AppearanceModel.load(model, scheme)
    reader = VideoReader(video)
    info = reader.info
    tracker = Tracker(model, **(tracker_options or {}))
    smoother = StreamSmoother(smooth, info.fps)
    n_lost = 0
    interrupted = False
    prog = Progress(info.n_frames or None, desc="keyshape track", enabled=show_progress)
    t0 = time.perf_counter()
    with contextlib.ExitStack() as stack:
        f = stack.enter_context(atomic_write(output))
        writer = TracksWriter(f, model.n_points)
        vw = stack.enter_context(video_writer(overlay, info.fps, (info.width, info.height))) if overlay else None

        def emit(items):
            for pts, (res, frame) in items:
                writer.write(res.index, res.index / info.fps, res.confidence, res.success, pts, res.pose)
                if vw is not None:
                    img = draw_shape(frame, pts, model.scheme_) if res.success else frame.copy()
                    if not res.success:
                        cv2.putText(img, "lost", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 255), 2)
                    vw.write(img)

        try:
            for i, frame in reader:
                res = tracker.step(frame, i)
                n_lost += not res.success
                emit(smoother.push(res.points, (res, frame if vw is not None else None)))
                prog.update()
        except KeyboardInterrupt:
            interrupted = True
        emit(smoother.flush())
        prog.close()
    n = writer.n_rows
    dt = time.perf_counter() - t0
    truncated = (not interrupted) and reader.truncated
    msg = (f"keyshape track: {n} frames, {n_lost} lost, {n / max(dt, 1e-9):.0f} frames/s -> {output}"
           + (f" and {overlay}" if overlay else ""))
    if interrupted:
        msg += f" (interrupted: tracks written for frames 0-{n - 1} only)"
    return TrackSummary(n, info.n_frames, n_lost, n / max(dt, 1e-9), truncated, interrupted, msg)
