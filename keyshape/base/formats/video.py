"""Video reading and writing with OpenCV: streamed, validated, written atomically.

Frames are ``uint8`` BGR arrays of shape ``(height, width, 3)`` (OpenCV order), or gray
``(height, width)`` ones; ``luma`` gray frames come from the decoder's luma plane without the colour
conversion (:func:`luma_table`). Reading streams one frame at a time, so memory does not grow with the length
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


def _open(path: Path, raw: bool = False) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        cap.release()
        raise InputError("cannot open as a video (unknown format or corrupt file)", path)
    if raw:                                  # the decoder's own picture: its first plane, no colour conversion
        cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
    return cap


@contextlib.contextmanager
def opencv_log(level: int) -> Iterator[None]:
    """OpenCV's own log at ``level`` (``cv2.utils.logging.LOG_LEVEL_*``) while the block runs."""
    old = cv2.utils.logging.setLogLevel(level)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(old)


def _read_raw(cap: cv2.VideoCapture):
    """``cap.read()`` without OpenCV's once-per-process warning that the raw picture format (yuv420p) "will be
    treated as 8UC1": that is what is wanted here."""
    with opencv_log(cv2.utils.logging.LOG_LEVEL_ERROR):
        return cap.read()


def open_capture(path: str | Path, table: np.ndarray | None = None) -> cv2.VideoCapture:
    """OpenCV's capture of ``path`` (one-line error naming it where it cannot be opened); with a
    :func:`luma_table`, one that hands out the decoder's luma plane (read it with :func:`read_frame`)."""
    return _open(Path(path), raw=table is not None)


def read_frame(cap: cv2.VideoCapture, table: np.ndarray | None = None):
    """``(ok, frame)`` of ``cap.read()``; with ``table`` (the capture opened with it, :func:`open_capture`) the
    luma plane through the table: the gray frame of the BGR one."""
    if table is None:
        return cap.read()
    ok, frame = _read_raw(cap)
    return ok, (cv2.LUT(frame, table) if ok and frame is not None else frame)


def luma_table(path: str | Path) -> np.ndarray | None:
    """The 256-entry table that maps the decoder's luma plane of ``path`` to the gray frame OpenCV's BGR
    decoding and ``cvtColor(BGR2GRAY)`` give, or None where no table does (the gray frames then come
    from the BGR ones).

    The gray of the BGR made from a luma and two chroma values is the luma again, rescaled (from video range
    where the stream is in it) and rounded: the table is the least-squares line of the BGR's gray on the luma
    over the first frame, rounded. Accepted where that frame, decoded both ways, is a single-plane ``uint8``
    picture of the frame's size with a luma spread of 8 levels or more, the line's slope is 0.95-1.25 and the
    table is within 0.75 gray levels of the BGR's gray on average and 3 levels on 99.9% of the pixels.
    """
    path = Path(path)
    try:
        cap = _open(path, raw=True)
        ok, y = _read_raw(cap)
        cap.release()
        cap = _open(path)
        ok2, bgr = cap.read()
        cap.release()
    except (InputError, cv2.error):
        return None
    if not (ok and ok2) or y is None or bgr is None or y.dtype != np.uint8 or bgr.ndim != 3 \
            or y.shape != bgr.shape[:2] or float(y.std()) < 8.0:
        return None
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    a, b = np.polyfit(y.ravel().astype(np.float64), gray.ravel().astype(np.float64), 1)
    if not 0.95 <= a <= 1.25:
        return None
    table = np.clip(np.round(a * np.arange(256) + b), 0, 255).astype(np.uint8)
    d = cv2.absdiff(cv2.LUT(y, table), gray)
    if float(d.mean()) > 0.75 or float(np.percentile(d, 99.9)) > 3.0:
        return None
    return table


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
    luma : bool
        With ``gray``: decode the luma plane alone where :func:`luma_table` finds it gives the BGR's gray
        (to within the colour conversion's rounding), skipping the colour conversion; the BGR's gray otherwise.
        ``luma_table_`` says which (None: from BGR).
    """

    def __init__(self, path: str | Path, gray: bool = False, luma: bool = False):
        self.info = video_info(path)
        self.path = self.info.path
        self.gray = gray
        self.luma_table_ = luma_table(self.path) if gray and luma else None
        self.n_read = 0
        self.truncated = False

    def __len__(self) -> int:
        return self.info.n_frames

    def _convert(self, frame: np.ndarray) -> np.ndarray:
        # a luma frame is gray already (read_frame)
        return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if self.gray and self.luma_table_ is None else frame

    def _capture(self) -> cv2.VideoCapture:
        return open_capture(self.path, self.luma_table_)

    def _read(self, cap: cv2.VideoCapture):
        return read_frame(cap, self.luma_table_)

    def __iter__(self) -> Iterator[tuple[int, np.ndarray]]:
        cap = self._capture()
        self.n_read = 0
        try:
            while True:
                ok, frame = self._read(cap)
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

        With ``seek`` (default) the decoder is positioned by OpenCV's frame seek (frame-exact on the constant-rate mp4
        and avi files tested), and where OpenCV reports another position than ``start`` the frames before it are
        decoded and discarded, as they always are without ``seek``. Afterwards ``n_read`` is the index after the last
        frame decoded and ``truncated`` says whether a read to the end stopped before the announced frame count.
        """
        start = max(0, int(start))
        cap = self._capture()
        i = got = 0
        try:
            if start > 0:
                if not (seek and cap.set(cv2.CAP_PROP_POS_FRAMES, start)
                        and int(round(cap.get(cv2.CAP_PROP_POS_FRAMES))) == start):
                    cap.release()
                    cap = self._capture()
                    while i < start and cap.grab():
                        i += 1
                    if i < start:
                        return
                i = start
            while stop is None or i < stop:
                ok, frame = self._read(cap)
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
