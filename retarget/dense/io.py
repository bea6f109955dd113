"""File formats of the dense-mesh tools: SEQUENCE.npz, KEYPOINTS.json, PAIRS.json, marker and mask JSON.

* ``SEQUENCE.npz``: ``vertices`` (n_frames, n_points, 3) float, frame 0 the
  rest face, every frame in the same point order; ``faces`` (n_faces, 3) int
  (zero-based triangles; optional for ``keypoints``, required for ``transfer`` output).
* ``KEYPOINTS.json``: ``{"indices": [rest vertex index, ...], "history": [...]}``.
* ``PAIRS.json``: ``[{"reference": R, "target": T}, ...]``, R and T a vertex
  index (zero-based) or ``[x, y, z]``.
* markers JSON: ``{"name": vertex index or [x, y, z], ...}`` (a bare list of
  indices is named ``"0"``, ``"1"``...); placed markers are written as
  ``{"name": {"position": [x, y, z], "vertex": nearest target vertex}}``.
* masks JSON: ``{"name": [vertex index, ...], ...}`` (discontinuity masks as vertex groups),
  or the masks file of ``keyshape mocap`` (``{"regions": [{"name", "vertices", ...}], ...}``,
  docs/mocap.md): its regions' ``vertices`` are carried to the target and everything else
  (allowed markers, images) is written back unchanged, so the output feeds ``keyshape mocap --masks``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_path, atomic_write


def _json(path: str | Path, what: str):
    path = require_file(path, what)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", path) from None


def read_sequence(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read SEQUENCE.npz: (vertices (n_frames, n_points, 3) float64, faces (n_faces, 3) or None)."""
    path = require_file(path, "sequence")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "vertices" not in z:
                raise InputError(f"no 'vertices' array (found: {', '.join(z.files) or 'none'})", path)
            v = np.asarray(z["vertices"], np.float64)
            f = np.asarray(z["faces"]) if "faces" in z else None
    except (OSError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"not a readable .npz file ({exc})", path) from None
    if v.ndim != 3 or v.shape[2] != 3 or v.shape[0] < 2:
        raise InputError(f"'vertices' must be (n_frames >= 2, n_points, 3), got {v.shape}", path)
    if not np.all(np.isfinite(v)):
        raise InputError("'vertices' contains NaN or infinite values", path)
    if f is not None:
        if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
            raise InputError(f"'faces' must be (n_faces, 3) integers, got {f.shape} {f.dtype}", path)
        if f.size and (f.min() < 0 or f.max() >= v.shape[1]):
            raise InputError(f"'faces' names vertices outside 0..{v.shape[1] - 1}", path)
        f = f.astype(np.intp)
    return v, f


def write_sequence(path: str | Path, vertices: np.ndarray, faces: np.ndarray | None = None) -> None:
    """Write SEQUENCE.npz atomically."""
    arrays = {"vertices": np.asarray(vertices, np.float64)}
    if faces is not None:
        arrays["faces"] = np.asarray(faces, np.int64)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)


def read_keypoints(path: str | Path, n_points: int | None = None) -> np.ndarray:
    """Read KEYPOINTS.json (``{"indices": [...]}`` or a bare list) -> (n_keys,) int indices."""
    data = _json(path, "key points")
    idx = data.get("indices") if isinstance(data, dict) else data
    if not isinstance(idx, list) or not idx or not all(isinstance(i, int) and not isinstance(i, bool) for i in idx):
        raise InputError("expected {\"indices\": [vertex index, ...]}", path)
    idx = np.array(idx, np.intp)
    if n_points is not None and (idx.min() < 0 or idx.max() >= n_points):
        raise InputError(f"key point indices must lie in 0..{n_points - 1}", path)
    return idx


def write_keypoints(path: str | Path, indices: np.ndarray, history: list | None = None) -> None:
    with atomic_write(path) as f:
        json.dump({"indices": [int(i) for i in indices], "history": history or []}, f, indent=1)


def read_pairs(path: str | Path) -> list:
    """Read PAIRS.json (validated against the meshes by :func:`~retarget.dense.registration.resolve_landmarks`)."""
    data = _json(path, "landmark pairs")
    if not isinstance(data, list):
        raise InputError("expected a list of {\"reference\": R, \"target\": T}", path)
    return data


def read_markers(path: str | Path, what: str = "markers") -> dict:
    """Read a markers JSON -> {name: vertex index or [x, y, z]}.

    Values may also be ``{"position": [x, y, z], "vertex": i}`` as :func:`place_markers` output
    is written (``keyshape register --out-markers``); the position is used.
    """
    data = _json(path, what)
    if isinstance(data, list):
        data = {str(i): m for i, m in enumerate(data)}
    if not isinstance(data, dict) or not data:
        raise InputError("expected {\"name\": vertex index or [x, y, z], ...}", path)
    out = {}
    for k, m in data.items():
        if isinstance(m, dict) and "position" in m:
            m = m["position"]
        ok = (isinstance(m, int) and not isinstance(m, bool)) or (
            isinstance(m, list) and len(m) == 3 and all(isinstance(c, (int, float)) for c in m))
        if not ok:
            raise InputError(f"marker {k!r}: expected a vertex index or [x, y, z], got {m!r:.60}", path)
        out[str(k)] = m
    return out


def read_masks(path: str | Path) -> dict:
    """Read a masks JSON -> {name: (n,) int vertex indices} (for a mocap masks file: the regions
    that list ``vertices``)."""
    data = _json(path, "masks")
    if isinstance(data, dict) and isinstance(data.get("regions"), list):
        groups = {}
        for i, r in enumerate(data["regions"]):
            if not isinstance(r, dict):
                raise InputError(f"regions[{i}]: expected an object", path)
            if "vertices" in r:
                groups[str(r.get("name", i))] = r["vertices"]
        if not groups:
            raise InputError("no region lists 'vertices' (image and vertex-group regions need no carrying)", path)
        data = groups
    if not isinstance(data, dict) or not data:
        raise InputError("expected {\"name\": [vertex index, ...], ...}", path)
    out = {}
    for k, m in data.items():
        if not isinstance(m, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in m):
            raise InputError(f"mask {k!r}: expected a list of vertex indices", path)
        out[k] = np.array(m, np.intp)
    return out


def write_masks(path: str | Path, masks: dict, source: str | Path) -> None:
    """Write carried masks ``{name: indices}`` in the layout of the ``source`` masks file."""
    spec = _json(source, "masks")
    if isinstance(spec, dict) and isinstance(spec.get("regions"), list):
        for i, r in enumerate(spec["regions"]):
            if "vertices" in r:
                r["vertices"] = masks[str(r.get("name", i))].tolist()
        write_json(path, spec)
    else:
        write_json(path, {k: v.tolist() for k, v in masks.items()})


def write_json(path: str | Path, data) -> None:
    with atomic_write(path) as f:
        json.dump(data, f, indent=1)
