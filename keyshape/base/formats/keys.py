"""KEYS.json (key shapes per region) and WEIGHTS.csv (per-frame weights): readers and writers.

KEYS.json::

    {"format": "keyshape-keys", "version": 1, "scheme": "contours48", "n_points": 48,
     "coordinates": "model frame (head pose removed)",
     "regions": {"mouth": {"method": "spread", "points": [28, ..., 47],
                           "neutral": [[x, y], ...],
                           "keys": [{"name": "mouth_0", "frame": 123, "from_frame": true,
                                     "shape": [[x, y], ...]}, ...]},
                 "eyes": {...}}}

``frame`` is the video frame number (the tracks file's ``frame`` column) the key
was taken from (for k-means centres of mass, ``from_frame`` is false and
``frame`` is the nearest frame). ``neutral`` is the mean shape the weights are
relative to: a frame is ``neutral + sum_i w_i (key_i - neutral)``.

WEIGHTS.csv: header ``frame,mouth_0,...,mouth_7,eyes_0,...,interpolated``; one row
per frame of the tracks file; ``interpolated`` is 1 where the tracker failed on
that frame (``success=0``) and the weights were filled in from neighbouring frames.
"""
from __future__ import annotations

import io as _io
import json
import re
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_write
from keyshape.decompose.regions import REGIONS, RegionKeys

FORMAT = "keyshape-keys"
_NAME = re.compile(r"([a-z]+)_(\d+)")


def write_keys(path: str | Path, scheme_name: str, n_points: int, regions: list[RegionKeys]) -> None:
    """Write key shapes of one or more regions to a KEYS.json file, atomically."""
    data = {"format": FORMAT, "version": 1, "scheme": scheme_name, "n_points": int(n_points),
            "coordinates": "model frame (head pose removed)", "regions": {}}
    for rk in regions:
        data["regions"][rk.region] = {
            "method": rk.method, "points": [int(i) for i in rk.points],
            "neutral": np.round(rk.neutral, 6).tolist(),
            "keys": [{"name": name, "frame": int(f), "from_frame": bool(ff), "shape": np.round(s, 6).tolist()}
                     for name, f, ff, s in zip(rk.names, rk.frames, rk.from_frame, rk.keys)]}
    with atomic_write(path) as f:
        json.dump(data, f, indent=1)
        f.write("\n")


def read_keys(path: str | Path) -> tuple[str, int, list[RegionKeys]]:
    """Read a KEYS.json file: (scheme name, n_points, [RegionKeys, ...]); errors name the file."""
    path = require_file(path, "key-shapes file")
    try:
        data = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", path) from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"not a key-shapes file: expected \"format\": \"{FORMAT}\" "
                         f"(write one with 'keyshape select')", path)
    try:
        scheme, n_points = str(data["scheme"]), int(data["n_points"])
        out = []
        for region, r in data["regions"].items():
            if region not in REGIONS:
                raise InputError(f"unknown region {region!r}: expected one of {', '.join(REGIONS)}", path)
            pts = np.array(r["points"], dtype=np.intp)
            neutral = np.array(r["neutral"], dtype=np.float64)
            keys = np.array([k["shape"] for k in r["keys"]], dtype=np.float64)
            frames = np.array([k["frame"] for k in r["keys"]], dtype=np.int64)
            ff = np.array([k.get("from_frame", True) for k in r["keys"]], dtype=bool)
            if not len(keys):
                raise InputError(f"region {region!r} has no key shapes", path)
            if neutral.shape != (len(pts), 2) or keys.shape != (len(keys), len(pts), 2):
                raise InputError(f"region {region!r}: {len(pts)} points, but neutral has shape {neutral.shape} "
                                 f"and keys {keys.shape}", path)
            if (pts < 0).any() or (pts >= n_points).any():
                raise InputError(f"region {region!r} names points outside 0..{n_points - 1}", path)
            names = [k.get("name") for k in r["keys"]]
            expected = [f"{region}_{i}" for i in range(len(keys))]
            if names != expected:
                raise InputError(f"region {region!r}: key names must be {expected[0]}..{expected[-1]} in "
                                 f"order, got {names[:3]}...", path)
            out.append(RegionKeys(region, str(r.get("method", "")), pts, frames, keys, neutral, ff))
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"malformed key-shapes file (missing or bad field: {exc})", path) from None
    if not out:
        raise InputError("no regions in key-shapes file", path)
    return scheme, n_points, out


def write_weights(path: str | Path, frames: np.ndarray, names: list[str], weights: np.ndarray,
                  interpolated: np.ndarray | None = None) -> None:
    """Write WEIGHTS.csv: ``frame``, one column per key shape (``REGION_K``), ``interpolated``."""
    frames = np.asarray(frames)
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (len(frames), len(names)):
        raise InputError(f"weights: expected shape ({len(frames)}, {len(names)}), got {weights.shape}")
    for n in names:
        if not _NAME.fullmatch(n):
            raise InputError(f"weight column name {n!r} is not REGION_K (e.g. mouth_0)")
    interp = np.zeros(len(frames)) if interpolated is None else np.asarray(interpolated, dtype=float)
    buf = _io.StringIO()
    np.savetxt(buf, np.column_stack([frames, weights, interp]),
               fmt=["%d"] + ["%.6f"] * len(names) + ["%d"], delimiter=",")
    with atomic_write(path) as f:
        f.write(",".join(["frame", *names, "interpolated"]) + "\n")
        f.write(buf.getvalue())


def read_weights(path: str | Path) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
    """Read WEIGHTS.csv: (frames (n,), names, weights (n, n_keys), interpolated (n,) bool)."""
    path = require_file(path, "weights file")
    lines = Path(path).read_text().splitlines()
    if not lines:
        raise InputError("empty file: expected a header 'frame,mouth_0,...'", path, 1)
    header = [h.strip() for h in lines[0].split(",")]
    if header[0] != "frame":
        raise InputError(f"first column must be 'frame', got {header[0]!r}", path, 1)
    has_flag = header[-1] == "interpolated"
    names = header[1:-1] if has_flag else header[1:]
    bad = [n for n in names if not _NAME.fullmatch(n)]
    if bad or not names:
        raise InputError(f"weight columns must be named REGION_K (e.g. mouth_0); got {bad[:3] or 'none'}", path, 1)
    rows = []
    for ln, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        parts = line.split(",")
        if len(parts) != len(header):
            raise InputError(f"{len(parts)} fields, expected {len(header)}", path, ln)
        try:
            rows.append([float(v) for v in parts])
        except ValueError:
            raise InputError(f"not a number in {line[:60]!r}", path, ln) from None
    if not rows:
        raise InputError("no data rows", path, 2)
    a = np.array(rows)
    if not np.isfinite(a).all():
        raise InputError("NaN or infinite weights", path)
    w = a[:, 1:1 + len(names)]
    flag = a[:, -1] != 0 if has_flag else np.zeros(len(a), dtype=bool)
    return a[:, 0].astype(np.int64), names, w, flag
