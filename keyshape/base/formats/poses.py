"""POSES.json (a pose library: rig weights per key shape) and rig landmark JSON: readers and writers.

Design notes and figures: docs/formats.md, "Notes on the code", ``keyshape/base/formats/poses.py``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import write_json

FORMAT = "keyshape-poses"
LANDMARKS_FORMAT = "keyshape-rig-landmarks"
#: the widest rig shape range a pose library may declare (curves are clipped to its range)
MAX_RANGE = 10.0


def _load_json(path: Path, what: str):
    path = require_file(path, what)
    try:
        return json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", path) from None


def write_poses(path: str | Path, data: dict) -> None:
    """Write a pose library (the dict layout of the module docstring) atomically."""
    out = dict(data)
    out["format"], out["version"] = FORMAT, 1
    def rounded(pose: dict) -> dict:
        # rounded first, then the zeros left out: a weight that rounds to 0 is an absent shape, never a
        # written 0 that a range excluding 0 would refuse on reading
        pose = {s: round(float(v), 5) for s, v in pose.items()}
        return {s: v for s, v in pose.items() if v != 0}

    regions = {}
    for r, reg in data["regions"].items():
        regions[r] = {"shapes": list(reg["shapes"]), "neutral": rounded(reg.get("neutral", {})),
                      "keys": {k: rounded(pose) for k, pose in reg["keys"].items()}}
    out["regions"] = regions
    write_json(path, out, end="\n")


def read_poses(path: str | Path, rig_shapes: list[str] | None = None) -> dict:
    """Read and check a POSES.json file.

    Parameters
    ----------
    rig_shapes : names of the rig's shapes; when given every shape the file names must be one.

    Raises
    ------
    InputError
        Naming the file: wrong format, a weight that is not a number or lies outside
        ``range``, a key pose naming a shape outside its region's ``shapes`` or the rig.
    """
    path = Path(path)
    data = _load_json(path, "poses file")
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"not a poses file: expected \"format\": \"{FORMAT}\" (write one with 'keyshape pose')",
                         path)
    try:
        rng = data.get("range", [0.0, 1.0])
        if not isinstance(rng, list) or len(rng) != 2 or \
                any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in rng):
            raise InputError(f"range {rng!r}: expected [low, high] numbers", path)
        lo, hi = (float(x) for x in rng)
        if not (np.isfinite(lo) and np.isfinite(hi) and -MAX_RANGE <= lo < hi <= MAX_RANGE):
            raise InputError(f"range [{lo:g}, {hi:g}]: must be finite numbers with {-MAX_RANGE:g} <= low < high <= "
                             f"{MAX_RANGE:g} (blendshapes: [0, 1])", path)
        regions = data["regions"]
        if not isinstance(regions, dict) or not regions:
            raise InputError("no regions", path)
        known = set(rig_shapes) if rig_shapes is not None else None
        for r, reg in regions.items():
            shapes = [str(s) for s in reg["shapes"]]
            if known is not None:
                bad = [s for s in shapes if s not in known]
                if bad:
                    raise InputError(f"region {r!r} names shape(s) {bad[:5]} the rig lacks "
                                     f"(rig shapes: {', '.join(sorted(known)[:8])}...)", path)
            allowed = set(shapes)
            poses = {"neutral": reg.get("neutral", {}), **reg["keys"]}
            for key, pose in poses.items():
                if not isinstance(pose, dict):
                    raise InputError(f"region {r!r}, {key!r}: expected an object {{shape: weight}}", path)
                for s, v in pose.items():
                    if s not in allowed:
                        where = "the rig lacks" if known is not None and s not in known else \
                            f"is not among region {r!r}'s shapes"
                        raise InputError(f"region {r!r}, {key!r}: shape {s!r} {where}", path)
                    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                        raise InputError(f"region {r!r}, {key!r}: weight of {s!r} is not a finite number: {v!r}",
                                         path)
                    if not lo - 1e-9 <= v <= hi + 1e-9:
                        raise InputError(f"region {r!r}, {key!r}: weight {v} of {s!r} is outside the rig's "
                                         f"range [{lo:g}, {hi:g}]", path)
            reg["shapes"] = shapes
        data["range"] = [lo, hi]
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"malformed poses file (missing or bad field: {exc})", path) from None
    return data


def write_rig_landmarks(path: str | Path, scheme: str, n_vertices: int, points: list) -> None:
    """Write a rig landmark JSON (see the module docstring)."""
    data = {"format": LANDMARKS_FORMAT, "version": 1, "scheme": scheme, "n_vertices": int(n_vertices),
            "points": points}
    write_json(path, data, indent=None, end="\n")


def read_rig_landmarks(path: str | Path, n_vertices: int | None = None) -> tuple[str, np.ndarray]:
    """Read a rig landmark JSON: (scheme name, (n_points, n_vertices_used) sparse as a dense weight matrix).

    Returns
    -------
    scheme : str
    W : (n_points, n_vertices) float64 with rows summing to 1: ``points = W @ vertices``.
        (n_vertices from the file's ``n_vertices``.)
    """
    path = Path(path)
    data = _load_json(path, "rig landmark file")
    if not isinstance(data, dict) or data.get("format") != LANDMARKS_FORMAT:
        raise InputError(f"not a rig landmark file: expected \"format\": \"{LANDMARKS_FORMAT}\"", path)
    try:
        nv = int(data["n_vertices"])
        scheme = str(data["scheme"])
        pts = data["points"]
        if n_vertices is not None and nv != n_vertices:
            raise InputError(f"landmarks are for a rig of {nv} vertices, this rig has {n_vertices}", path)
        W = np.zeros((len(pts), nv))
        for i, p in enumerate(pts):
            pairs = [[p, 1.0]] if isinstance(p, int) else p
            for v, w in pairs:
                if not 0 <= int(v) < nv:
                    raise InputError(f"point {i}: vertex {v} outside 0..{nv - 1}", path)
                W[i, int(v)] += float(w)
        if not np.isfinite(W).all():
            raise InputError(f"point {int(np.flatnonzero(~np.isfinite(W).all(axis=1))[0])}: a vertex weight is "
                             "not a finite number", path)
        s = W.sum(axis=1)
        if np.any(np.abs(s - 1) > 1e-6):
            raise InputError(f"point {int(np.argmax(np.abs(s - 1)))}: vertex weights must sum to 1", path)
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"malformed rig landmark file (missing or bad field: {exc})", path) from None
    if len(W) >= 3 and len(np.unique(W, axis=0)) < 3:
        raise InputError(f"the {len(W)} points sit on {len(np.unique(W, axis=0))} place(s) of the rig: a degenerate "
                         "landmark map (every point on one vertex?)", path)
    return scheme, W


def read_landmark_list(path: str | Path) -> np.ndarray | None:
    """Read a rig's published landmark vertex list (see the module docstring): (n,) int array, zero-based;
    None when the file is a keyshape-rig-landmarks JSON (read it with :func:`read_rig_landmarks`)."""
    path = require_file(path, "rig landmark file")
    try:
        text = Path(path).read_text()
    except UnicodeDecodeError:
        raise InputError("not a landmark file (not text)", path) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError:
        data = None
        rows = []
        for i, line in enumerate(text.splitlines(), 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            try:
                rows.append(int(line))
            except ValueError:
                raise InputError(f"line {i}: {line[:40]!r} is not a vertex index (one index a line, or a JSON list)",
                                 path) from None
        if not rows:
            raise InputError("no vertex indices (one index a line, or a JSON list)", path)
        return np.asarray(rows, np.int64)
    if isinstance(data, dict) and data.get("format") == LANDMARKS_FORMAT:
        return None
    if isinstance(data, dict) and "idx_to_landmark_verts" in data:            # ICT-FaceKit's vertex_indices.json
        data = data["idx_to_landmark_verts"]
    if not isinstance(data, list) or not data or not all(isinstance(v, int) and not isinstance(v, bool) for v in data):
        raise InputError(f"not a rig landmark file: expected a keyshape-rig-landmarks JSON (\"format\": "
                         f"\"{LANDMARKS_FORMAT}\") or a list of vertex indices", path)
    return np.asarray(data, np.int64)
