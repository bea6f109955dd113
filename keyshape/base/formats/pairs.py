"""PAIRS.json: landmark pairs between two meshes (``keyshape register``, ``keyshape transfer``); reader.

``[{"reference": R, "target": T}, ...]``, R and T a vertex index (zero-based) or
``[x, y, z]``; checked against the meshes by
:func:`keyshape.retarget.dense.registration.resolve_landmarks`. keyshape does not write it.
"""
from __future__ import annotations

from pathlib import Path

from keyshape.base.errors import InputError
from keyshape.base.files import read_json


def read_pairs(path: str | Path) -> list:
    """Read PAIRS.json: a list of ``{"reference": R, "target": T}`` (validated against the meshes later)."""
    data = read_json(path, "landmark pairs")
    if not isinstance(data, list):
        raise InputError("expected a list of {\"reference\": R, \"target\": T}", path)
    return data
