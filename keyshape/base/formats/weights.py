"""WEIGHTS.csv: per-frame key-shape weights (or retargeted curves); the one reader and writer.

Design notes and figures: docs/formats.md, "Notes on the code", ``keyshape/base/formats/weights.py``.
"""
from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_write
from keyshape.base.formats.tracks import check_frame_numbers, rate_from_times

FLAG = "interpolated"
TIME = "time"
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
    odd = [n for n in names if not n or any(c in n for c in ',"\r\n') or n in ("frame", TIME, FLAG)]
    if odd:
        raise InputError(f"column names must be non-empty, without commas, quotes or line breaks and not "
                         f"'frame'/'{TIME}'/'{FLAG}'; got {odd[:3]}", path, line)


#: largest plausible weight magnitude (weights are about 0..1; far beyond is a damaged file)
MAX_WEIGHT = 1e6


def read_weights(path: str | Path, key_names: bool = False) -> WeightsTable:
    """Read a WEIGHTS.csv (with or without the ``time`` column; older files' leading comments skipped).

    Parameters
    ----------
    path : the file
    key_names : also require the columns to be named ``REGION_K`` (decompose's output)

    Raises
    ------
    InputError
        Naming the file and line for a bad header, a short row, a non-number or a NaN.
    """
    return _read(path, key_names)[0]


def _read(path, key_names: bool = False) -> tuple[WeightsTable, np.ndarray | None, list[str]]:
    """The table, the ``time`` column (None where the file has none) and the leading comment lines."""
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
    comments, rows = [",".join(r) for r in rows[:skip]], rows[skip:]
    if not rows or not rows[0] or rows[0][0].strip() != "frame":
        raise InputError("expected a header 'frame,time,<key shape>,...'", path, 1 + skip)
    names = [c.strip() for c in rows[0][1:]]
    timed = bool(names) and names[0] == TIME
    if timed:
        names = names[1:]
    flag = bool(names) and names[-1] == FLAG
    if flag:
        names = names[:-1]
    _check_names(names, path, 1 + skip, key_names)
    n_cols = len(names) + 1 + timed + flag
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
        col = (["frame", *([TIME] if timed else []), *names, FLAG])[j]
        raise InputError(f"{a[i, j]} in column {col!r} (weights must be finite numbers)", path, body[i][0])
    time = a[:, 1] if timed else None
    w = a[:, 1 + timed:1 + timed + len(names)]
    big = np.abs(w) > MAX_WEIGHT
    if big.any():
        i, j = np.argwhere(big)[0]
        raise InputError(f"{w[i, j]:g} in column {names[j]!r}: implausible weight (beyond +-{MAX_WEIGHT:g})",
                         path, body[i][0])
    if flag and not np.isin(a[:, -1], (0, 1)).all():
        i = int(np.flatnonzero(~np.isin(a[:, -1], (0, 1)))[0])
        raise InputError(f"'{FLAG}' must be 0 or 1, got {a[i, -1]:g}", path, body[i][0])
    check_frame_numbers(a[:, 0], path, [ln for ln, _ in body],
                        "one row per frame is needed for an animation at a steady rate")
    interp = a[:, -1] != 0 if flag else np.zeros(len(a), dtype=bool)
    return WeightsTable(a[:, 0].astype(np.int64), names, w, interp), time, comments


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


def _plausible(fps: float) -> float | None:
    return fps if np.isfinite(fps) and 0 < fps < 1e6 else None


def read_weights_fps(path: str | Path) -> float | None:
    """The take's frame rate: from the ``time`` column (frames over seconds between the first and the
    last row, :func:`~keyshape.base.formats.tracks.rate_from_times`), or from an older file's leading
    comment (``# keyshape weights, fps=24``); None where the file gives neither (no ``time`` column,
    or a single frame)."""
    table, time, comments = _read(path)
    if time is not None:
        fps = rate_from_times(float(table.frames[-1] - table.frames[0]), float(time[-1] - time[0]))
        return None if fps is None else _plausible(fps)
    for line in comments:
        m = _FPS.search(line)
        if m:
            return _plausible(float(m.group(1)))
    return None


def write_weights(path: str | Path, frames: np.ndarray, names: list[str], weights: np.ndarray,
                  interpolated: np.ndarray | None = None, fps: float | None = None) -> None:
    """Write a WEIGHTS.csv atomically: ``frame``, with ``fps`` the ``time`` column (``frame / fps``),
    one ``%.6f`` column per name, then ``interpolated`` (0/1) when ``interpolated`` is given."""
    frames = np.asarray(frames)
    names = [str(n) for n in names]
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (len(frames), len(names)):
        raise InputError(f"weights: expected shape {(len(frames), len(names))}, got {weights.shape}", path)
    _check_names(names, path)
    _check_writable(frames, names, weights, path)
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise InputError(f"frame rate must be a positive number, got {fps}; nothing written", path)
    timed = fps is not None
    header = ["frame", *([TIME] if timed else []), *names]
    # one %-format per row (Python's "%.6f", as np.char.mod gives it, a few times faster)
    fmt = ",".join(["%d"] + ["%.6f"] * (timed + len(names)) + (["%d"] if interpolated is not None else []))
    fr = frames.astype(np.int64)
    rows = [fr.tolist(), *([(fr / float(fps)).tolist()] if timed else []), *weights.T.tolist()]
    if interpolated is not None:
        rows.append(np.asarray(interpolated).astype(bool).astype(int).tolist())
        header.append(FLAG)
    with atomic_write(path) as f:
        f.write(",".join(header) + "\n")
        if len(frames):
            f.write("\n".join(fmt % r for r in zip(*rows)) + "\n")
