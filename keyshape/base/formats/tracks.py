"""Tracks CSV (OpenFace-style landmark tracks, :class:`Tracks`); reader and writers.

Design notes and figures: docs/formats.md, "Notes on the code", ``keyshape/base/formats/tracks.py``.
"""
from __future__ import annotations

import hashlib
import io as _io
import json
import warnings
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_path, read_json, write_json
from keyshape.base.schemes import AUX_NAME

POSE_COLUMNS = ("pose_a11", "pose_a12", "pose_tx", "pose_a21", "pose_a22", "pose_ty")
#: first line of a tracks file an interrupted ``keyshape track`` wrote (``NAME.partial.csv``)
PARTIAL_MARK = "# keyshape partial tracks:"


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
    meta : dict, e.g. ``{"model": "sha256:...", "scheme": "contours48"}`` (empty when unknown)
    aux : dict[str, (n_frames, k, 2) float64], the auxiliary points of each group (``nose``), image
        pixels; empty when the tracks have none
    """

    frame: np.ndarray
    time: np.ndarray
    confidence: np.ndarray
    success: np.ndarray
    points: np.ndarray
    pose: np.ndarray
    meta: dict = field(default_factory=dict)
    aux: dict = field(default_factory=dict)

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
        self.aux = {str(k): np.asarray(v, dtype=np.float64) for k, v in self.aux.items()}
        for k, v in self.aux.items():
            if v.ndim != 3 or v.shape[0] != n or v.shape[2] != 2 or not re.fullmatch(AUX_NAME, k):
                raise InputError(f"Tracks.aux[{k!r}]: expected a lower-case name and shape ({n}, k, 2), "
                                 f"got {v.shape}")

    @property
    def n_frames(self) -> int:
        return len(self.frame)

    @property
    def n_points(self) -> int:
        return self.points.shape[1]

    @property
    def image_size(self) -> tuple[int, int] | None:
        """(width, height) in pixels of the frames the points were tracked in (the metadata's
        ``image_size``), or None where unrecorded or not two positive whole numbers."""
        size = self.meta.get("image_size") if isinstance(self.meta, dict) else None
        if (isinstance(size, (list, tuple)) and len(size) == 2
                and all(isinstance(v, (int, float)) and v >= 1 and float(v).is_integer() for v in size)):
            return int(size[0]), int(size[1])
        return None

    @property
    def fps(self) -> float | None:
        """The video's frame rate: what the tracker recorded (the metadata's ``fps``), else, for tracks written
        without it, the median of the timestamps' steps rounded to 3 decimals; None where neither gives one."""
        fps = self.meta.get("fps") if isinstance(self.meta, dict) else None
        if isinstance(fps, (int, float)) and not isinstance(fps, bool) and np.isfinite(fps) and 0 < fps < 1e6:
            return float(fps)
        dt = np.diff(self.time)
        dt = dt[np.isfinite(dt) & (dt > 0)]
        return round(float(1.0 / np.median(dt)), 3) if len(dt) else None

    def __getitem__(self, idx) -> "Tracks":
        return Tracks(self.frame[idx], self.time[idx], self.confidence[idx], self.success[idx],
                      self.points[idx], self.pose[idx], dict(self.meta), {k: v[idx] for k, v in self.aux.items()})


def tracks_header(n_points: int, aux: dict | None = None, pose: bool = True) -> list[str]:
    """The columns of a tracks CSV of ``n_points`` points and the auxiliary groups ``aux`` (name -> k)."""
    return (["frame", "time", "confidence", "success"] + [f"x_{i}" for i in range(n_points)]
            + [f"y_{i}" for i in range(n_points)] + (list(POSE_COLUMNS) if pose else [])
            + [f"{g}_{c}_{i}" for g, k in (aux or {}).items() for c in "xy" for i in range(k)])


def write_tracks(path: str | Path, tracks: Tracks) -> None:
    """Write ``tracks`` as a tracks CSV, atomically (NaN is written as an empty field)."""
    n, p = tracks.n_frames, tracks.n_points
    aux = [a[:, :, c] for a in tracks.aux.values() for c in (0, 1)]
    data = np.column_stack([tracks.frame, tracks.time, tracks.confidence, tracks.success.astype(float),
                            tracks.points[:, :, 0], tracks.points[:, :, 1], tracks.pose.reshape(n, 6), *aux])
    buf = _io.StringIO()
    fmt = ["%d", "%.6f", "%.4f", "%d"] + ["%.4f"] * (2 * p) + ["%.8g"] * 6 + ["%.4f"] * sum(a.shape[1] for a in aux)
    np.savetxt(buf, data, fmt=fmt, delimiter=",")
    header = tracks_header(p, {k: v.shape[1] for k, v in tracks.aux.items()})
    text = ",".join(header) + "\n" + buf.getvalue().replace("nan", "")
    # the CSV's bytes reach the disk first, then the sidecar replaces the old one, then the CSV is
    # renamed into place: a full disk fails before anything is replaced (old CSV and old sidecar stay)
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="\n") as f:        # the bytes on disk are the text hashed
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        write_meta(path, tracks.meta, hashlib.sha256(text.encode()).hexdigest())


META_PREFIX = "# keyshape-tracks "
#: key that marks a JSON file as a tracks sidecar written by keyshape
META_KEY = "keyshape_tracks"


def meta_path(path: str | Path) -> Path:
    """The metadata sidecar of a tracks CSV: ``NAME.csv`` -> ``NAME.meta.json``."""
    path = Path(path)
    return path.with_name(path.stem + ".meta.json")


def write_meta(path: str | Path, meta: dict | None, csv_sha256: str) -> None:
    """Write the sidecar of the tracks CSV ``path`` (whose text hashes to ``csv_sha256``), atomically.

    With no metadata, a sidecar keyshape wrote earlier is removed (it would describe
    other tracks); a file of that name that keyshape did not write is left alone.
    """
    side = meta_path(path)
    if meta:
        write_json(side, {META_KEY: 1, "csv_sha256": csv_sha256, **meta})
    elif side.is_file():
        try:
            old = json.loads(side.read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            return
        from keyshape.base.files import may_delete
        if isinstance(old, dict) and META_KEY in old and may_delete(side):
            side.unlink(missing_ok=True)


def _read_meta(path: Path, data: bytes) -> dict:
    """The sidecar's metadata for the CSV ``path`` whose bytes are ``data`` ({} if none, not keyshape's, or stale)."""
    side = meta_path(path)
    if not side.is_file():
        return {}
    meta = read_json(side, "tracks metadata sidecar")
    if not isinstance(meta, dict) or META_KEY not in meta:
        return {}                              # not ours: some other file of that name
    digest = meta.pop("csv_sha256", None)
    meta.pop(META_KEY)
    if digest != hashlib.sha256(data).hexdigest():
        warnings.warn(f"{side}: written for another version of {path.name} (the CSV changed since); "
                      "its metadata (model fingerprint) is ignored", stacklevel=3)
        return {}
    return meta


def check_frame_size(meta: dict, width: int, height: int, video=None, tracks_path=None) -> None:
    """Refuse drawing tracks on a video of another frame size than the one they were tracked in
    (``image_size`` in the tracks' metadata; tracks without it pass)."""
    size = meta.get("image_size") if isinstance(meta, dict) else None
    if (isinstance(size, list) and len(size) == 2 and width and height
            and [int(width), int(height)] != [int(v) for v in size if isinstance(v, (int, float))]):
        src = f" ({tracks_path})" if tracks_path is not None else ""
        raise InputError(f"the video's frames are {width}x{height} but the tracks{src} were tracked on "
                         f"{size[0]}x{size[1]} frames: is this the video the tracks came from?", video)


def meta_line(meta: dict | None) -> str:
    """The metadata line of a tracks CSV ('' for no metadata)."""
    return META_PREFIX + json.dumps(meta, sort_keys=True) + "\n" if meta else ""


def read_tracks(path: str | Path, accept_partial: bool = False) -> Tracks:
    """Read a tracks CSV. Raises :class:`InputError` naming file and line on malformed content.

    Empty fields (and ``nan``) read as NaN; the pose columns may be absent
    (identity pose assumed), so other trackers' OpenFace-style files can be read; auxiliary
    columns (``nose_x_0..``, after the others) read into ``Tracks.aux``.
    A file an interrupted ``keyshape track`` marked partial (first line
    :data:`PARTIAL_MARK`) is refused unless ``accept_partial``.
    """
    path = require_file(path, "tracks file")
    data = path.read_bytes()                   # read once: parsed here, hashed against the sidecar
    try:
        text = data.decode("utf-8-sig")         # a byte-order mark (spreadsheet exports) is not a column
    except UnicodeDecodeError:
        raise InputError("not a text CSV file", path) from None
    lines = text.splitlines()
    meta: dict = {} if lines and lines[0].startswith("#") else _read_meta(path, data)
    if lines and lines[0].startswith(PARTIAL_MARK):
        if not accept_partial:
            raise InputError("partial tracks from an interrupted 'keyshape track' "
                             f"({lines[0][len(PARTIAL_MARK):].strip()}); pass --accept-partial to use them anyway",
                             path, 1)
    skip = 0
    while skip < len(lines) and lines[skip].startswith("#"):
        if lines[skip].startswith(META_PREFIX):
            try:
                meta = json.loads(lines[skip][len(META_PREFIX):])
            except json.JSONDecodeError:
                raise InputError("broken '# keyshape-tracks' metadata line (not JSON)", path, skip + 1) from None
            if not isinstance(meta, dict):
                raise InputError("broken '# keyshape-tracks' metadata line (not a JSON object)", path, skip + 1)
        skip += 1
    lines = lines[skip:]
    first = skip + 1   # line number of the header
    if not lines or not lines[0].strip():
        raise InputError("empty file: expected a header row 'frame,time,confidence,success,x_0,...'", path, first)
    header = [h.strip() for h in lines[0].split(",")]
    xs = [h for h in header if re.fullmatch(r"x_\d+", h)]
    n_points = len(xs)
    if header[:4] != ["frame", "time", "confidence", "success"] or n_points == 0:
        raise InputError("header must start 'frame,time,confidence,success,x_0,...'", path, first)
    with_pose = all(c in header for c in POSE_COLUMNS)
    aux: dict = {}
    for h in header:
        if (m := re.fullmatch(rf"({AUX_NAME})_x_\d+", h)):
            aux[m.group(1)] = aux.get(m.group(1), 0) + 1
    expected = tracks_header(n_points, aux, with_pose)
    if header != expected:
        extra = [h for h in header if h not in expected]
        missing = [h for h in expected if h not in header]
        which = (f"extra column(s) {extra[:3]}" if extra else "") + ("; " if extra and missing else "") + \
            (f"missing column(s) {missing[:3]}" if missing else "") or "columns out of order"
        raise InputError(f"unexpected columns ({which}): expected {len(expected)} columns "
                         f"frame,time,confidence,success,x_0..x_{n_points - 1},y_0..y_{n_points - 1}"
                         f"{',pose_a11..pose_ty' if with_pose else ''}"
                         f"{''.join(f',{g}_x_0..{g}_y_{k - 1}' for g, k in aux.items())}", path, first)
    rows = []
    ncol = len(expected)
    lns = []
    for ln, line in enumerate(lines[1:], start=first + 1):
        if not line.strip():
            continue
        lns.append(ln)
        parts = line.split(",")
        if len(parts) != ncol:
            raise InputError(f"{len(parts)} fields, expected {ncol}", path, ln)
        try:
            rows.append([float(v) if v.strip() else np.nan for v in parts])
        except ValueError:
            bad = next(v for v in parts if v.strip() and not _is_float(v))
            raise InputError(f"not a number: {bad.strip()!r}", path, ln) from None
    if not rows:
        raise InputError("no data rows", path, first + 1)
    a = np.array(rows, dtype=np.float64)
    n = len(a)
    for col, name in ((0, "frame"), (3, "success")):
        if np.isnan(a[:, col]).any():
            ln = lns[int(np.flatnonzero(np.isnan(a[:, col]))[0])]
            raise InputError(f"empty {name} field", path, ln)
    _check_track_values(a, header, path, lns)
    end = 4 + 2 * n_points
    pose = a[:, end:end + 6].reshape(n, 2, 3) if with_pose else np.broadcast_to(
        np.array([[1.0, 0, 0], [0, 1.0, 0]]), (n, 2, 3)).copy()
    pts = np.stack([a[:, 4:4 + n_points], a[:, 4 + n_points:end]], axis=-1)
    _check_not_collapsed(pts, a[:, 3] != 0, path, lns)
    i = end + (6 if with_pose else 0)
    extra = {}
    for g, k in aux.items():
        extra[g] = np.stack([a[:, i:i + k], a[:, i + k:i + 2 * k]], axis=-1)
        i += 2 * k
    return Tracks(a[:, 0].astype(np.int64), a[:, 1], a[:, 2], a[:, 3] != 0, pts, pose, meta, extra)


def _check_not_collapsed(pts: np.ndarray, success: np.ndarray, path, lns: list[int]) -> None:
    """A tracked frame (success 1) whose points all lie on one spot (spread under 1e-3 px) is no face:
    the maths downstream divides by the face's size. Refused naming the first such row."""
    if pts.shape[1] < 2:
        return
    rows = np.flatnonzero(success & np.isfinite(pts).all(axis=(1, 2)))
    p = pts[rows]
    spread = np.abs(p - p.mean(axis=1, keepdims=True)).max(axis=(1, 2)) if len(rows) else np.zeros(0)
    bad = spread < 1e-3
    if bad.any():
        i = int(rows[np.flatnonzero(bad)[0]])
        raise InputError(f"the {pts.shape[1]} points of a tracked frame lie on one spot (collapsed; "
                         f"{int(bad.sum())} such frame(s)): not a tracked face", path, lns[i])


#: largest plausible pixel coordinate or pose translation (no video is 100 000 pixels wide)
MAX_PIXELS = 1e5


def _check_track_values(a: np.ndarray, header: list[str], path, lns: list[int]) -> None:
    """Sense checks of the parsed rows: finite, plausible values; frame numbers whole, unique,
    sorted and contiguous; success 0 or 1."""
    def fail(row: int, col: int, why: str):
        raise InputError(f"{header[col]} = {a[row, col]!r}: {why}", path, lns[row])

    inf = np.isinf(a)
    if inf.any():
        r, c = np.argwhere(inf)[0]
        fail(r, c, "not a finite number")
    if ((a[:, 3] != 0) & (a[:, 3] != 1)).any():
        fail(int(np.flatnonzero((a[:, 3] != 0) & (a[:, 3] != 1))[0]), 3, "success must be 0 or 1")
    big = np.abs(np.nan_to_num(a[:, 4:])) > MAX_PIXELS
    if big.any():
        r, c = np.argwhere(big)[0]
        fail(r, c + 4, f"implausible (beyond {MAX_PIXELS:g} pixels)")
    t = a[:, 1]
    if (np.abs(np.nan_to_num(t)) > 1e7).any():
        fail(int(np.flatnonzero(np.abs(np.nan_to_num(t)) > 1e7)[0]), 1, "implausible time (seconds)")
    from keyshape.base.options import FPS_MAX
    steps = np.diff(t[np.isfinite(t)])
    steps = steps[steps > 0]
    if len(steps) and np.median(steps) < 1.0 / FPS_MAX:
        raise InputError(f"the times advance by {np.median(steps):.3g} s per frame (median), faster than "
                         f"{FPS_MAX:g} frames per second: not a frame clock (times that do not advance)", path)
    check_frame_numbers(a[:, 0], path, lns, "keyshape needs one row per frame (write the missing frames "
                        "with success=0 and empty coordinates)")


def rate_from_times(n_steps: float, span: float, resolution: float = 1e-6) -> float | None:
    """The frame rate of ``n_steps`` frame steps over ``span`` seconds of times written to
    ``resolution`` (``%.6f``: a span known to within 1e-6 s), with the fewest significant digits
    consistent with them: 24 reads back as 24, 30000/1001 as 29.97003 from a long take. None where
    the span is too short to tell."""
    if not (n_steps > 0 and span > resolution):
        return None
    lo, hi, rate = n_steps / (span + resolution), n_steps / (span - resolution), n_steps / span
    for digits in range(1, 10):
        r = float(f"{rate:.{digits}g}")
        if lo <= r <= hi:
            return r
    return rate


def check_frame_numbers(fr: np.ndarray, path, lines: list[int], gap_hint: str) -> None:
    """Frame numbers whole, from 0, unique, increasing and contiguous (one row per frame), else an
    :class:`InputError` naming ``path`` and the line (``lines[i]`` of row ``i``); ``gap_hint`` says
    what a gap breaks. Shared by the tracks and WEIGHTS.csv readers."""
    bad = (fr != np.round(fr)) | (fr < 0) | (fr > 1e9)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"frame {fr[i]:g}: frame numbers must be whole numbers from 0", path, lines[i])
    step = np.diff(fr)
    if (step <= 0).any():
        i = int(np.flatnonzero(step <= 0)[0]) + 1
        why = "repeated" if step[i - 1] == 0 else f"out of order (after frame {int(fr[i - 1])})"
        raise InputError(f"frame {int(fr[i])} {why}: frame numbers must be unique and increasing", path, lines[i])
    if (step > 1).any():
        gaps = np.flatnonzero(step > 1)
        i = int(gaps[0])
        raise InputError(f"frame numbers jump from {int(fr[i])} to {int(fr[i + 1])} ({len(gaps)} gap(s), "
                         f"{int((step[gaps] - 1).sum())} frames missing): {gap_hint}", path, lines[i + 1])


def _is_float(v: str) -> bool:
    try:
        float(v)
        return True
    except ValueError:
        return False


class TracksWriter:
    """Write a tracks CSV row by row to an open text file (streaming: memory does not grow with length).

    Use inside :func:`keyshape.base.files.atomic_write` so an interrupted run never
    leaves a file that looks complete unless it is finished deliberately.
    """

    def __init__(self, f, n_points: int, aux: dict | None = None):
        self.f = f
        self.n_points = n_points
        self.aux = dict(aux or {})                  # group -> number of points, written after the pose
        self.n_rows = 0
        # a row of finite values: one %-format (the same text as the per-field formats below) of the
        # values gathered in the columns' order from [points (x, y interleaved), pose]
        n_all = n_points + sum(self.aux.values())
        order = [np.arange(n_points) * 2, np.arange(n_points) * 2 + 1, 2 * n_all + np.arange(6)]
        start = n_points
        for k in self.aux.values():
            order += [(start + np.arange(k)) * 2, (start + np.arange(k)) * 2 + 1]
            start += k
        self._order, self._n_all = np.concatenate(order), n_all
        self._fmt = ",".join(["%d", "%.6f", "%.4f", "%d"] + ["%.4f"] * (2 * n_points) + ["%.8g"] * 6
                             + ["%.4f"] * (2 * sum(self.aux.values()))) + "\n"
        f.write(",".join(tracks_header(n_points, self.aux)) + "\n")

    def write(self, frame: int, time: float, confidence: float, success: bool, points: np.ndarray,
              pose: np.ndarray) -> None:
        """One row; ``points`` (n_points + the auxiliary points, 2): the scheme's, then each group's."""
        p = np.asarray(points, np.float64)
        n = self.n_points
        pose = np.asarray(pose, np.float64).ravel()
        if p.shape == (self._n_all, 2) and pose.shape == (6,):
            every = np.concatenate([p.ravel(), pose]).take(self._order)
            if np.isfinite(every).all():
                self.f.write(self._fmt % (int(frame), time, confidence, 1 if success else 0, *every.tolist()))
                self.n_rows += 1
                return
        vals = np.concatenate([p[:n, 0], p[:n, 1]]).tolist()     # Python floats: formatting without numpy scalars
        fields = [str(int(frame)), f"{time:.6f}", f"{confidence:.4f}", "1" if success else "0"]
        fields += [f"{v:.4f}" if math.isfinite(v) else "" for v in vals]
        fields += [f"{v:.8g}" if math.isfinite(v) else "" for v in pose.tolist()]
        for k in self.aux.values():
            fields += [f"{v:.4f}" if math.isfinite(v) else "" for v in
                       np.concatenate([p[n:n + k, 0], p[n:n + k, 1]]).tolist()]
            n += k
        self.f.write(",".join(fields) + "\n")
        self.n_rows += 1
