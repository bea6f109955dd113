"""Per-frame key-shape weights as CSV: ``frame`` then one column per key shape.

A reader for the decompose stage's output (``frame,mouth_0,...,eyes_0,...[,interpolated]``,
see ``decompose/io.py``) that also accepts any other column names (ARKit curves),
and a writer for retargeted curves (``frame,<target name>,...``), which is what
Maya and Blender import scripts read. A last column ``interpolated`` (decompose's
flag for frames filled in where tracking failed) is not a key shape and is dropped.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_write


def read_weights(path: str | Path) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Read a weights CSV.

    Returns
    -------
    frames : (n_frames,) int64
    names : list of n_keys column names
    weights : (n_frames, n_keys) float64

    Raises
    ------
    InputError
        Naming the file and line for a bad header, a short row, a non-number or a NaN.
    """
    path = require_file(path, "weights CSV")
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows or not rows[0] or rows[0][0].strip() != "frame":
        raise InputError("expected a header 'frame,<key shape>,...'", path, 1)
    names = [c.strip() for c in rows[0][1:]]
    flag = bool(names) and names[-1] == "interpolated"
    if not names or (flag and len(names) == 1):
        raise InputError("no key-shape columns after 'frame'", path, 1)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputError(f"duplicate columns {dup}", path, 1)
    body = [(i, r) for i, r in enumerate(rows[1:], start=2) if any(c.strip() for c in r)]
    if not body:
        raise InputError("no frames", path)
    for ln, r in body:
        if len(r) != len(names) + 1:
            raise InputError(f"{len(r)} fields, expected {len(names) + 1}", path, ln)
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
        col = "frame" if j == 0 else names[j - 1]
        raise InputError(f"{a[i, j]} in column {col!r} (weights must be finite numbers)", path, body[i][0])
    if flag:
        return a[:, 0].astype(np.int64), names[:-1], a[:, 1:-1]
    return a[:, 0].astype(np.int64), names, a[:, 1:]


def write_weights(path: str | Path, frames: np.ndarray, names: list[str], weights: np.ndarray) -> None:
    """Write ``frame,<names>`` rows atomically (``%.6g`` values)."""
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (len(frames), len(names)):
        raise InputError(f"weights: expected shape {(len(frames), len(names))}, got {weights.shape}", path)
    with atomic_write(path, newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", *names])
        for fr, row in zip(frames, weights):
            w.writerow([int(fr), *("%.6g" % x for x in row)])
