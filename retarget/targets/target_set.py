"""Target key shapes: the artist's models, one per source key shape (section 5 of 004_119ba07521a9af0b.txt).

Design notes and figures: docs/retarget.md, "Notes on the code", ``retarget/targets/target_set.py``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError, MissingFileError, require_file
from keyshape.base.files import read_json
from keyshape.base.formats.obj import Mesh, read_obj, read_obj_vertices

TARGET_SUFFIXES = (".obj", ".pts", ".json")
NEUTRAL_STEMS = ("neutral",)


@dataclass
class TargetSet:
    """Target key shapes in weight-column order.

    Attributes
    ----------
    columns : list of n_keys weight-column names (``REGION_K``)
    names : list of n_keys target names (file stems), used for morph targets and CSV headers
    shapes : (n_keys, n_vertices, dim) float64, dim 3 for meshes, 2 for drawings
    files : list of n_keys Paths
    neutral : (n_vertices, dim) float64 or None
    mesh : Mesh or None, the topology of 3D targets (from the neutral, else the first target)
    """

    columns: list
    names: list
    shapes: np.ndarray
    files: list
    neutral: np.ndarray | None = None
    mesh: Mesh | None = None

    @property
    def dim(self) -> int:
        return int(self.shapes.shape[2])

    @property
    def n_vertices(self) -> int:
        return int(self.shapes.shape[1])


def name_key(name: str) -> str:
    """Normalised name for matching: case-insensitive, ``_L``/``Left`` and ``_R``/``Right`` alike."""
    n = name.strip().lower()
    n = re.sub(r"[_\-. ]?(l|left)$", "left", n) if re.search(r"([_\-. ]l|left)$", n) else n
    n = re.sub(r"[_\-. ]?(r|right)$", "right", n) if re.search(r"([_\-. ]r|right)$", n) else n
    return n


def read_points(path: str | Path) -> np.ndarray:
    """Read a 2D drawing: ``.pts`` or JSON (``[[x, y], ...]`` or ``{"points": [[x, y], ...]}``)."""
    path = require_file(path, "target drawing")
    if path.suffix.lower() == ".pts":
        from keyshape.base.formats.labels import read_pts
        return read_pts(path)
    data = read_json(path)
    if isinstance(data, dict):
        if "points" not in data:
            raise InputError("expected a list of [x, y] or an object with 'points'", path)
        data = data["points"]
    try:
        pts = np.asarray(data, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("points must be a list of [x, y] number pairs", path) from None
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) == 0:
        raise InputError(f"points must have shape (n_points, 2), got {pts.shape}", path)
    if not np.all(np.isfinite(pts)):
        raise InputError("non-finite point coordinate", path)
    return pts


def _is_3d(path: Path) -> bool:
    return path.suffix.lower() == ".obj"


def _candidates(sources: Sequence[str | Path] | str | Path) -> tuple[list[Path], Path | None]:
    """Files given (a folder or a list of files) and the folder, if one was given."""
    if isinstance(sources, (str, Path)):
        sources = [sources]
    files, folder = [], None
    for s in sources:
        p = Path(s)
        if p.is_dir():
            folder = p
            files += sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in TARGET_SUFFIXES
                            and not q.name.startswith("."))    # hidden: keyshape's manifest, editors' files
        else:
            files.append(require_file(p, "target"))
    refuse_name_twins(files, "targets whose names differ only by case or extension")
    if not files:
        where = folder if folder is not None else ", ".join(map(str, sources))
        raise InputError(f"no target files ({'/'.join(TARGET_SUFFIXES)}) found", where)
    return files, folder


def refuse_name_twins(files: Sequence[Path], what: str) -> None:
    """One-line :class:`InputError` for two ``files`` whose names differ only by case (jawOpen.obj and JawOpen.obj
    are one file on some systems; which one is meant?); ``what`` names them in the message."""
    seen: dict[str, Path] = {}
    for f in files:
        key = f.stem.casefold()
        if key in seen and seen[key] != f:
            raise InputError(f"two {what}: {seen[key].name} and {f.name} (which one is meant?); rename or remove one",
                             f.parent)
        seen[key] = f


def read_mapping(path: str | Path) -> dict[str, Path]:
    """Read a mapping JSON ``{"REGION_K": "file", ...}``; paths are relative to the mapping file."""
    path = require_file(path, "mapping JSON")
    data = read_json(path)
    if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
        raise InputError('expected an object {"REGION_K": "target file", ...}', path)
    out = {}
    for k, v in data.items():
        p = Path(v) if Path(v).is_absolute() else path.parent / v
        if not p.is_file():
            raise MissingFileError(p, f"target for column {k!r} named in mapping {path}")
        out[k] = p
    return out


def load_targets(columns: Sequence[str], sources: Sequence[str | Path] | str | Path | None = None,
                 mapping: str | Path | dict | None = None, neutral: str | Path | None = None) -> TargetSet:
    """Load one target per weight column.

    Parameters
    ----------
    columns : the weight columns (``REGION_K``) in order
    sources : a folder or a list of target files (may be None when ``mapping`` names every file)
    mapping : mapping JSON path or dict column -> path; without it, column names are matched to
        file stems case-insensitively
    neutral : optional neutral mesh/drawing; without it the mapping's ``"neutral"`` entry, else a
        file with stem ``neutral`` among the sources, is used when no column is named ``neutral``

    Raises
    ------
    InputError
        A column with no target (naming the column and where targets were looked for),
        targets of different vertex counts or dimensions (naming the file), broken files.
    MissingFileError
        A mapping or source that names a missing file.
    """
    columns = list(columns)
    files, folder = _candidates(sources) if sources is not None else ([], None)
    if isinstance(mapping, (str, Path)):
        mapping_src = Path(mapping)
        chosen = read_mapping(mapping)
    elif isinstance(mapping, dict):
        mapping_src, chosen = None, {k: Path(v) for k, v in mapping.items()}
        for k, p in chosen.items():
            if not p.is_file():
                raise MissingFileError(p, f"target for column {k!r}")
    else:
        mapping_src, chosen = None, {}
    by_key = {name_key(f.stem): f for f in reversed(files)}          # the first file of a name
    col_keys = {name_key(c) for c in columns}
    if neutral is None:  # a mapping's "neutral" entry, else a file named neutral.* among the sources
        for s in NEUTRAL_STEMS:
            if s in chosen and s not in col_keys:
                neutral = chosen.pop(s)
            elif s in by_key and s not in col_keys:
                neutral = by_key[s]
    paths = [chosen.get(c) or by_key.get(name_key(c)) for c in columns]
    missing = [c for c, p in zip(columns, paths) if p is None]
    if missing:
        where = mapping_src or folder or "the target files given"
        avail = ", ".join(sorted(f.stem for f in files)[:12]) or "none"
        raise InputError(f"weight column(s) {missing} have no target (looked in {where}; "
                         f"target files: {avail}); give --map MAP.json or name files after the columns")
    kinds = {_is_3d(p) for p in paths} | ({_is_3d(Path(neutral))} if neutral is not None else set())
    if len(kinds) > 1:
        raise InputError("targets mix OBJ meshes and 2D drawings; use one kind", paths[0])
    is3d = kinds.pop()
    mesh = None
    neutral_arr = None
    if is3d:
        ref = Path(neutral) if neutral is not None else paths[0]
        mesh = read_obj(ref, require_faces=False)
        n = mesh.n_vertices
        if neutral is not None:
            neutral_arr = mesh.vertices
        cache: dict[Path, np.ndarray] = {}
        shapes = []
        for p in paths:
            if p not in cache:
                cache[p] = mesh.vertices if (neutral is None and p == ref) else read_obj_vertices(p, n)
            shapes.append(cache[p])
    else:
        shapes = [read_points(p) for p in paths]
        if neutral is not None:
            neutral_arr = read_points(neutral)
        n = len(neutral_arr) if neutral_arr is not None else len(shapes[0])
        for p, s in zip(paths, shapes):
            if len(s) != n:
                raise InputError(f"{len(s)} points, expected {n} (targets must share one point set)", p)
    return TargetSet(columns, [p.stem for p in paths], np.stack(shapes), paths, neutral_arr, mesh)


def column_region(column: str) -> str:
    """Region of a ``REGION_K`` weight column (``mouth_3`` -> ``mouth``)."""
    head, sep, tail = column.rpartition("_")
    return head if sep and tail.isdigit() else column


def read_regions(path: str | Path, mesh: Mesh | None = None) -> dict[str, np.ndarray]:
    """Read region vertex groups.

    ``path`` is a JSON object ``{"mouth": [vertex indices...], "eyes": "eyes_group", ...}``
    (a string value names an OBJ group of ``mesh``), or an OBJ whose ``g`` groups are the regions.
    """
    path = require_file(path, "regions file")
    if path.suffix.lower() == ".obj":
        m = read_obj(path)
        if not m.groups:
            raise InputError("OBJ has no groups ('g' lines) to use as regions", path)
        return {k: m.group_vertices(k) for k in m.groups}
    data = read_json(path, "regions file")
    if not isinstance(data, dict) or not data:
        raise InputError('expected an object {"region": [vertex indices] or "OBJ group name", ...}', path)
    out = {}
    for k, v in data.items():
        if isinstance(v, str):
            if mesh is None:
                raise InputError(f"region {k!r} names group {v!r} but the targets are not meshes", path)
            try:
                out[k] = mesh.group_vertices(v)
            except InputError as e:
                raise InputError(f"region {k!r}: {e}", path) from None
        else:
            try:
                idx = np.asarray(v, dtype=np.float64)
            except (TypeError, ValueError):
                raise InputError(f"region {k!r}: expected a list of vertex indices", path) from None
            if idx.ndim != 1 or idx.size == 0 or np.any(idx != np.round(idx)) or np.any(np.abs(idx) > 1e9):
                raise InputError(f"region {k!r}: expected a non-empty list of integer vertex indices", path)
            if idx.min() < 0:
                raise InputError(f"region {k!r}: negative vertex index {int(idx.min())}", path)
            out[k] = idx.astype(np.intp)
        if mesh is not None and (out[k].min() < 0 or out[k].max() >= mesh.n_vertices):
            raise InputError(f"region {k!r}: vertex index outside 0..{mesh.n_vertices - 1}", path)
    return out


def key_regions(columns: Sequence[str], regions: dict[str, np.ndarray], source: str | Path = "regions") \
        -> tuple[list[str], np.ndarray]:
    """Region names used by ``columns`` and each column's region index (names matched case-insensitively)."""
    lookup = {k.lower(): k for k in regions}
    names: list[str] = []
    idx = []
    for c in columns:
        r = column_region(c).lower()
        if r not in lookup:
            raise InputError(f"column {c!r} is in region {column_region(c)!r}, which has no vertex group "
                             f"(regions: {', '.join(regions)})", source)
        if lookup[r] not in names:
            names.append(lookup[r])
        idx.append(names.index(lookup[r]))
    return names, np.array(idx, dtype=np.intp)
