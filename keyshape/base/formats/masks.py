"""Masks JSON: discontinuity masks, which vertices the bones of which markers may move; reader and writer.

Design notes and figures: docs/formats.md, "Notes on the code", ``keyshape/base/formats/masks.py``.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import read_json, write_json

_SOURCES = ("vertices", "vertex_group", "image_value")


@dataclass
class Masks:
    """A masks file in memory.

    Attributes
    ----------
    spec : dict
        The file's JSON object in the regions layout (``{"regions": [...], ...}``); a plain
        ``{"name": [indices]}`` file is held as ``{"regions": [{"name": ..., "vertices": ...}]}``.
    plain : bool
        The file was the plain layout (it is written back the same way).
    image : ndarray or None
        The label image ``spec["image"]`` names (read where a region uses ``image_value``).
    path : Path or None
        The file, for error messages.
    """

    spec: dict
    plain: bool = False
    image: np.ndarray | None = None
    path: Path | None = None

    @property
    def regions(self) -> list:
        return self.spec["regions"]

    def region_name(self, k: int) -> str:
        return str(self.regions[k].get("name", f"region{k}"))

    def vertex_lists(self) -> dict:
        """``{region name: (n,) intp vertex indices}`` of the regions that list ``vertices``."""
        return {self.region_name(k): np.asarray(r["vertices"], np.intp)
                for k, r in enumerate(self.regions) if "vertices" in r}

    def with_vertex_lists(self, groups: dict) -> "Masks":
        """A copy whose regions' ``vertices`` are ``groups[name]`` (everything else unchanged)."""
        spec = copy.deepcopy(self.spec)
        for k, r in enumerate(spec["regions"]):
            if "vertices" in r:
                r["vertices"] = [int(i) for i in groups[self.region_name(k)]]
        return Masks(spec, self.plain, self.image, self.path)


def _int_list(v) -> bool:
    return isinstance(v, list) and all(isinstance(i, int) and not isinstance(i, bool) for i in v)


def read_masks(path: str | Path) -> Masks:
    """Read a masks JSON (and the label image it names, where a region uses ``image_value``).

    Raises
    ------
    InputError
        Naming the file: not JSON, neither layout, a region without ``vertices``,
        ``vertex_group`` or ``image_value``, a vertex list that is not integers, a missing image.
    """
    path = require_file(path, "masks file")
    data = read_json(path, "masks file")
    plain = False
    if isinstance(data, dict) and "regions" in data:
        if not isinstance(data["regions"], list):
            raise InputError("expected a JSON object with a 'regions' list", path)
    elif isinstance(data, dict) and data and all(_int_list(v) for v in data.values()):
        data, plain = {"regions": [{"name": str(k), "vertices": v} for k, v in data.items()]}, True
    else:
        raise InputError("expected a JSON object with a 'regions' list (or {\"name\": [vertex index, ...]})", path)
    for k, r in enumerate(data["regions"]):
        if not isinstance(r, dict):
            raise InputError(f"regions[{k}]: expected an object", path)
        name = r.get("name", f"region{k}")
        if not any(s in r for s in _SOURCES):
            raise InputError(f"region {name!r}: give 'vertices', 'vertex_group' or 'image_value'", path)
        if "vertices" in r and not _int_list(r["vertices"]):
            raise InputError(f"region {name!r}: expected a list of vertex indices", path)
    image = None
    if any("image_value" in r for r in data["regions"]):
        if "image" not in data:
            raise InputError("a region uses 'image_value' but the file names no 'image'", path)
        import cv2

        ip = require_file(path.parent / data["image"], "mask image")
        image = cv2.imread(str(ip), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise InputError("not a readable image", ip)
    return Masks(data, plain, image, path)


def write_masks(path: str | Path, masks: Masks) -> None:
    """Write ``masks`` as a masks JSON (compact), atomically; a plain file stays plain."""
    if masks.plain:
        write_json(path, {masks.region_name(k): r["vertices"] for k, r in enumerate(masks.regions)}, indent=None)
    else:
        write_json(path, masks.spec, indent=None)
