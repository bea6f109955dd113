"""Video reading and writing with OpenCV: streamed, validated, written atomically.

Frames are ``uint8`` BGR arrays of shape ``(height, width, 3)`` (OpenCV order).
Reading streams one frame at a time, so memory does not grow with the length
of the video. The headless OpenCV wheel writes ``mp4v`` (.mp4) and ``MJPG``
(.avi); H.264 is not available there.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_path


@dataclass
class VideoInfo:
    """What the container says about a video (``n_frames`` may be an estimate)."""

    path: Path
    width: int
    height: int
    fps: float
    n_frames: int


def _open(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        cap.release()
        raise InputError("cannot open as a video (unknown format or corrupt file)", path)
    return cap


def video_info(path: str | Path) -> VideoInfo:
    """Open ``path`` and return its size, frame rate and frame count, or raise naming the file."""
    path = require_file(path, "video")
    cap = _open(path)
    try:
        info = VideoInfo(path, int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                         float(cap.get(cv2.CAP_PROP_FPS) or 0.0), int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0))
    finally:
        cap.release()
    if info.width <= 0 or info.height <= 0:
        raise InputError("video has no decodable picture size", path)
    if info.fps <= 0 or not np.isfinite(info.fps):
        info.fps = 30.0
    return info


class VideoReader:
    """Stream the frames of a video.

    Iterating yields ``(index, frame)``; after iteration, ``truncated`` is True
    when the stream ended before the frame count the container announced
    (a cut or damaged file) and ``n_read`` says how many frames decoded.
    ``read_frames`` seeks to given frames.

    Parameters
    ----------
    path : str or Path
    gray : bool
        Yield single-channel ``uint8`` frames instead of BGR.
    """

    def __init__(self, path: str | Path, gray: bool = False):
        self.info = video_info(path)
        self.path = self.info.path
        self.gray = gray
        self.n_read = 0
        self.truncated = False

    def __len__(self) -> int:
        return self.info.n_frames

    def _convert(self, frame: np.ndarray) -> np.ndarray:
        return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if self.gray else frame

    def __iter__(self) -> Iterator[tuple[int, np.ndarray]]:
        cap = _open(self.path)
        self.n_read = 0
        try:
            while True:
                ok, frame = cap.read()
                if not ok or frame is None:
                    break
                yield self.n_read, self._convert(frame)
                self.n_read += 1
        finally:
            cap.release()
        if self.n_read == 0:
            raise InputError("video has no decodable frames", self.path)
        self.truncated = self.info.n_frames > 0 and self.n_read < self.info.n_frames

    def frames(self, start: int = 0, stop: int | None = None, seek: bool = True) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(index, frame)`` for frames ``start`` to ``stop`` (exclusive; None: the end).

        With ``seek`` (default) the decoder is positioned with OpenCV's frame seek (FFmpeg seeks to
        the key frame before ``start`` and decodes forward to it): frame-exact on the constant-rate
        mp4 and avi files tested (``tests/test_chunked_tracking.py`` compares the frames with a
        sequential decode, byte for byte), and where OpenCV reports another position than ``start``
        the frames before it are decoded and discarded instead. Without ``seek`` they always are
        (exact on any file; slower). A caller that must be sure compares frames it also has from a
        sequential decode (:mod:`keyshape.tracker.chunked` compares checksums at its seams).
        Afterwards ``n_read`` is the index after the last frame decoded (0 if none was), and
        ``truncated`` says whether a read to the end stopped before the announced frame count.
        """
        start = max(0, int(start))
        cap = _open(self.path)
        i = got = 0
        try:
            if start > 0:
                if not (seek and cap.set(cv2.CAP_PROP_POS_FRAMES, start)
                        and int(round(cap.get(cv2.CAP_PROP_POS_FRAMES))) == start):
                    cap.release()
                    cap = _open(self.path)
                    while i < start and cap.grab():
                        i += 1
                    if i < start:
                        return
                i = start
            while stop is None or i < stop:
                ok, frame = cap.read()
                if not ok or frame is None:
                    break
                got += 1
                yield i, self._convert(frame)
                i += 1
        finally:
            cap.release()
            self.n_read = i if (got or start == 0) else 0
        if stop is None or i < stop:
            self.truncated = self.info.n_frames > 0 and self.n_read < self.info.n_frames

    def read_frames(self, indices) -> np.ndarray:
        """Decode the frames at ``indices`` (any order); raises naming frames past the end."""
        indices = np.asarray(indices, dtype=np.intp)
        want = set(int(i) for i in indices)
        got: dict[int, np.ndarray] = {}
        if want:
            last = max(want)
            for i, frame in self:
                if i in want:
                    got[i] = frame
                if i >= last:
                    break
        missing = sorted(want - set(got))
        if missing:
            raise InputError(f"frames {missing[:5]}{'...' if len(missing) > 5 else ''} are beyond the "
                             f"video's end ({self.n_read} frames decoded)", self.path)
        return np.stack([got[int(i)] for i in indices]) if len(indices) else np.empty((0,))


@contextlib.contextmanager
def video_writer(path: str | Path, fps: float, size: tuple[int, int]) -> Iterator["cv2.VideoWriter"]:
    """Write a video atomically: frames go to a temporary file renamed over ``path`` on success.

    ``size`` is ``(width, height)``. ``.mp4`` uses ``mp4v``; ``.avi`` uses ``MJPG``.
    Frames passed to ``write`` must be BGR ``uint8`` of that size.
    """
    path = Path(path)
    codec = {".mp4": "mp4v", ".avi": "MJPG", ".mov": "mp4v"}.get(path.suffix.lower())
    if codec is None:
        raise InputError("video output must end in .mp4 or .avi", path)
    with atomic_path(path) as tmp:
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*codec), float(fps), tuple(int(s) for s in size))
        if not writer.isOpened():
            raise InputError(f"OpenCV cannot write {codec} video here", path)
        try:
            yield writer
        finally:
            writer.release()
