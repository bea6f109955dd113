"""SEQUENCE.npz: a dense mesh performance (every frame in the same point order); reader and writer.

* ``vertices`` (n_frames, n_points, 3) float, frame 0 the rest face;
* ``faces`` (n_faces, 3) int, zero-based triangles (optional for ``keyshape keypoints``,
  written by ``keyshape transfer``).
"""
from __future__ import annotations

import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_path


def read_sequence(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read SEQUENCE.npz: (vertices (n_frames, n_points, 3) float64, faces (n_faces, 3) or None)."""
    path = require_file(path, "sequence")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "vertices" not in z:
                raise InputError(f"no 'vertices' array (found: {', '.join(z.files) or 'none'})", path)
            v = np.asarray(z["vertices"], np.float64)
            f = np.asarray(z["faces"]) if "faces" in z else None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error, KeyError, MemoryError, OverflowError,
            SyntaxError, tokenize.TokenError, TypeError, RecursionError, AttributeError, IndexError) as exc:
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
