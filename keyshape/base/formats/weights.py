"""WEIGHTS.csv: per-frame key-shape weights (or retargeted curves); the one reader and writer.

Layout: a header ``frame,<name>,...[,interpolated]``, then one row per frame::

    frame,mouth_0,mouth_1,eyes_0,interpolated
    0,0.125000,0.000000,0.500000,0
    1,0.130000,0.000000,0.490000,1

* ``frame`` is the video frame number (an integer).
* One column per key shape. ``keyshape decompose`` names them ``REGION_K``
  (``mouth_0``...); ``keyshape retarget`` writes its target names, and any other
  names (ARKit curves such as ``jawOpen``) are read as they are.
* ``interpolated`` (optional last column, written where the writer is given the
  flags) is 1 where the tracker failed on that frame (``success=0``) and the
  weights were filled in from neighbouring frames; it is not a key shape.
* Values are written ``%.6f``; any finite decimal number is read.
* ``keyshape decompose`` starts the file with a comment line giving the take's frame rate,
  ``# keyshape weights, fps=24``, so that ``keyshape retarget`` without the tracks plays the
  animation at the take's rate (:func:`read_weights_fps`). Lines starting with ``#`` before the
  header are comments; files without them (older ones) read as before.
"""
from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_write
from keyshape.base.formats.tracks import check_frame_numbers

FLAG = "interpolated"
KEY_NAME = re.compile(r"([a-z]+)_(\d+)")


class WeightsTable(NamedTuple):
    """What :func:`read_weights` returns (unpacks as ``frames, names, weights, interpolated``).

    Attributes
    ----------
    frames : (n_frames,) int64
    names : list of n_keys column names
    weights : (n_frames, n_keys) float64
    interpolated : (n_frames,) bool, all False where the file has no ``interpolated`` column
    """

    frames: np.ndarray
    names: list
    weights: np.ndarray
    interpolated: np.ndarray


def _check_names(names, path, line=None, key_names: bool = False) -> None:
    if not names:
        raise InputError("no key-shape columns after 'frame'", path, line)
    if key_names:
        bad = [n for n in names if not KEY_NAME.fullmatch(n)]
        if bad:
            raise InputError(f"weight columns must be named REGION_K (e.g. mouth_0); got {bad[:3]}", path, line)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputError(f"duplicate columns {dup}", path, line)
    odd = [n for n in names if not n or any(c in n for c in ',"\r\n') or n in ("frame", FLAG)]
    if odd:
        raise InputError(f"column names must be non-empty, without commas, quotes or line breaks and not "
                         f"'frame'/'{FLAG}'; got {odd[:3]}", path, line)


#: largest plausible weight magnitude (weights are about 0..1; far beyond is a damaged file)
MAX_WEIGHT = 1e6


def read_weights(path: str | Path, key_names: bool = False) -> WeightsTable:
    """Read a WEIGHTS.csv.

    Parameters
    ----------
    path : the file
    key_names : also require the columns to be named ``REGION_K`` (decompose's output)

    Raises
    ------
    InputError
        Naming the file and line for a bad header, a short row, a non-number or a NaN.
    """
    path = require_file(path, "weights file")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:     # a byte-order mark is not part of 'frame'
            rows = list(csv.reader(f))
    except UnicodeDecodeError as exc:
        raise InputError(f"not a UTF-8 text CSV file (byte {exc.start})", path) from None
    except csv.Error as exc:
        raise InputError(f"not a readable CSV file ({exc})", path) from None
    skip = 0
    while skip < len(rows) and rows[skip] and rows[skip][0].lstrip().startswith("#"):
        skip += 1
    if skip:
        rows = rows[skip:]
    if not rows or not rows[0] or rows[0][0].strip() != "frame":
        raise InputError("expected a header 'frame,<key shape>,...'", path, 1 + skip)
    names = [c.strip() for c in rows[0][1:]]
    flag = bool(names) and names[-1] == FLAG
    if flag:
        names = names[:-1]
    _check_names(names, path, 1 + skip, key_names)
    n_cols = len(names) + 1 + flag
    body = [(i, r) for i, r in enumerate(rows[1:], start=2 + skip) if any(c.strip() for c in r)]
    if not body:
        raise InputError("no frames", path)
    for ln, r in body:
        if len(r) != n_cols:
            raise InputError(f"{len(r)} fields, expected {n_cols}", path, ln)
    try:
        a = np.array([r for _, r in body], dtype=np.float64)
    except ValueError:
        for ln, r in body:
            for c in r:
                try:
                    float(c)
                except ValueError:
                    raise InputError(f"not a number: {c!r}", path, ln) from None
        raise
    bad = ~np.isfinite(a)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        col = (["frame", *names, FLAG])[j]
        raise InputError(f"{a[i, j]} in column {col!r} (weights must be finite numbers)", path, body[i][0])
    big = np.abs(a[:, 1:1 + len(names)]) > MAX_WEIGHT
    if big.any():
        i, j = np.argwhere(big)[0]
        raise InputError(f"{a[i, j + 1]:g} in column {names[j]!r}: implausible weight (beyond +-{MAX_WEIGHT:g})",
                         path, body[i][0])
    if flag and not np.isin(a[:, -1], (0, 1)).all():
        i = int(np.flatnonzero(~np.isin(a[:, -1], (0, 1)))[0])
        raise InputError(f"'{FLAG}' must be 0 or 1, got {a[i, -1]:g}", path, body[i][0])
    check_frame_numbers(a[:, 0], path, [ln for ln, _ in body],
                        "one row per frame is needed for an animation at a steady rate")
    interp = a[:, -1] != 0 if flag else np.zeros(len(a), dtype=bool)
    return WeightsTable(a[:, 0].astype(np.int64), names, a[:, 1:1 + len(names)], interp)


def _check_writable(frames: np.ndarray, names: list[str], weights: np.ndarray, path) -> None:
    """Refuse, before writing, what :func:`read_weights` would refuse: no frames, frame numbers that
    are not whole, unique, increasing and contiguous, weights that are not finite or beyond
    +-:data:`MAX_WEIGHT` (an :class:`InputError` naming ``path``; nothing is written)."""
    if len(frames) == 0:
        raise InputError("no frames to write (a WEIGHTS.csv needs at least one); nothing written", path)
    try:
        fr = frames.astype(np.float64)
    except (TypeError, ValueError):
        raise InputError("frame numbers must be whole numbers from 0; nothing written", path) from None
    if fr.ndim != 1 or not np.isfinite(fr).all():
        raise InputError("frame numbers must be whole numbers from 0; nothing written", path)
    try:
        check_frame_numbers(fr, None, [None] * len(fr), "one row per frame is needed for an animation at a "
                            "steady rate")
    except InputError as exc:
        raise InputError(f"{exc}; nothing written", path) from None
    bad = ~np.isfinite(weights) | (np.abs(np.nan_to_num(weights)) > MAX_WEIGHT)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise InputError(f"weight {weights[i, j]:g} in column {names[j]!r} at frame {int(fr[i])}: weights must be "
                         f"finite numbers within +-{MAX_WEIGHT:g}; nothing written", path)


_FPS = re.compile(r"\bfps\s*=\s*([0-9]+(?:\.[0-9]*)?(?:[eE][-+]?[0-9]+)?)")


def read_weights_fps(path: str | Path) -> float | None:
    """The frame rate a WEIGHTS.csv's leading comment gives (``# keyshape weights, fps=24``), or None."""
    path = require_file(path, "weights file")
    try:
        with open(path, encoding="utf-8") as f:
            for line in f:
                if not line.lstrip().startswith("#"):
                    return None
                m = _FPS.search(line)
                if m:
                    fps = float(m.group(1))
                    return fps if np.isfinite(fps) and 0 < fps < 1e6 else None
    except UnicodeDecodeError:
        return None
    return None


def write_weights(path: str | Path, frames: np.ndarray, names: list[str], weights: np.ndarray,
                  interpolated: np.ndarray | None = None, fps: float | None = None) -> None:
    """Write a WEIGHTS.csv atomically: ``frame``, one ``%.6f`` column per name, then ``interpolated``
    (0/1) when ``interpolated`` is given; with ``fps``, the leading comment ``# keyshape weights, fps=F``."""
    frames = np.asarray(frames)
    names = [str(n) for n in names]
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (len(frames), len(names)):
        raise InputError(f"weights: expected shape {(len(frames), len(names))}, got {weights.shape}", path)
    _check_names(names, path)
    _check_writable(frames, names, weights, path)
    header = ["frame", *names]
    # one %-format per row (Python's "%.6f", as np.char.mod gives it, a few times faster)
    fmt = ",".join(["%d"] + ["%.6f"] * len(names) + (["%d"] if interpolated is not None else []))
    rows = [frames.astype(np.int64).tolist(), *weights.T.tolist()]
    if interpolated is not None:
        rows.append(np.asarray(interpolated).astype(bool).astype(int).tolist())
        header.append(FLAG)
    with atomic_write(path) as f:
        if fps is not None:
            f.write(f"# keyshape weights, fps={float(fps):g}\n")
        f.write(",".join(header) + "\n")
        if len(frames):
            f.write("\n".join(fmt % r for r in zip(*rows)) + "\n")
