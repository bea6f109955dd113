"""KEYPOINTS.json (``keyshape keypoints``): key vertices of a dense sequence; reader and writer.

``{"indices": [rest vertex index, ...], "history": [...]}`` (a bare list of indices is read too).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.files import read_json, write_json


def read_keypoints(path: str | Path, n_points: int | None = None) -> np.ndarray:
    """Read KEYPOINTS.json (``{"indices": [...]}`` or a bare list) -> (n_keys,) int indices."""
    data = read_json(path, "key points")
    idx = data.get("indices") if isinstance(data, dict) else data
    if not isinstance(idx, list) or not idx or not all(isinstance(i, int) and not isinstance(i, bool) for i in idx):
        raise InputError("expected {\"indices\": [vertex index, ...]}", path)
    idx = np.array(idx, np.intp)
    if n_points is not None and (idx.min() < 0 or idx.max() >= n_points):
        raise InputError(f"key point indices must lie in 0..{n_points - 1}", path)
    return idx


def write_keypoints(path: str | Path, indices: np.ndarray, history: list | None = None) -> None:
    """Write KEYPOINTS.json atomically."""
    write_json(path, {"indices": [int(i) for i in indices], "history": history or []})
