"""Wavefront OBJ meshes: read and write with vertex order, polygons, UVs and groups kept.

A general mesh library (trimesh) merges or splits vertices at UV seams, which
breaks the one-to-one vertex correspondence blendshape targets rely on; this
reader keeps every ``v`` in file order. Polygons of any size are kept as
written (``polygons``) and fan-triangulated on demand (``triangles``).
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_write


@dataclass
class Mesh:
    """A polygon mesh.

    Attributes
    ----------
    vertices : (n_vertices, 3) float64
    polygons : list of (k,) int arrays, zero-based vertex indices per face
    uvs : (n_uvs, 2) float64, may be empty
    polygon_uvs : list of (k,) int arrays or None per face (zero-based ``vt`` indices)
    groups : dict of group name -> (n,) int array of face indices (``g`` lines)
    materials : dict of material name -> (n,) int array of face indices (``usemtl`` lines)
    material_colours : dict of material name -> (r, g, b) diffuse colour ``Kd`` from the ``mtllib``
        file beside the OBJ (only materials it defines)
    """

    vertices: np.ndarray
    polygons: list = field(default_factory=list)
    uvs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    polygon_uvs: list = field(default_factory=list)
    groups: dict = field(default_factory=dict)
    materials: dict = field(default_factory=dict)
    material_colours: dict = field(default_factory=dict)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def triangles(self) -> np.ndarray:
        """(n_triangles, 3) int array: every polygon fan-triangulated from its first vertex."""
        polys = [p for p in self.polygons if len(p) >= 3]
        if not polys:
            return np.zeros((0, 3), np.intp)
        flat = np.concatenate(polys).astype(np.intp)
        lens = np.fromiter(map(len, polys), np.intp, len(polys))
        start = np.cumsum(lens) - lens                       # each polygon's first vertex in ``flat``
        n_tri = lens - 2
        first = np.repeat(start, n_tri)
        k = np.arange(len(first)) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri) + 1   # 1 .. len - 2
        return np.stack([flat[first], flat[first + k], flat[first + k + 1]], axis=1)

    def group_vertices(self, name: str) -> np.ndarray:
        """Sorted vertex indices used by the faces of group ``name``."""
        if name not in self.groups:
            raise InputError(f"mesh has no group {name!r}; it has {', '.join(self.groups) or 'none'}")
        faces = self.groups[name]
        return np.unique(np.concatenate([self.polygons[i] for i in faces])) if len(faces) else np.zeros(0, np.intp)

    def with_vertices(self, vertices: np.ndarray) -> "Mesh":
        """A copy sharing topology, UVs and groups, with new vertex positions."""
        v = np.asarray(vertices, dtype=np.float64)
        if v.shape != self.vertices.shape:
            raise InputError(f"vertices: expected shape {self.vertices.shape}, got {v.shape}")
        return Mesh(v, self.polygons, self.uvs, self.polygon_uvs, self.groups, self.materials,
                    self.material_colours)


#: largest plausible vertex coordinate, mesh units (a face in micrometres is 2e5 wide)
MAX_COORDINATE = 1e7


def _floats(rows: list[str], path: Path, first_line: list[int], width: int, what: str) -> np.ndarray:
    try:
        arr = np.array([r.split()[1:width + 1] for r in rows], dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != width:
            raise ValueError
    except ValueError:
        for r, ln in zip(rows, first_line):
            parts = r.split()[1:width + 1]
            try:
                if len(parts) != width:
                    raise ValueError
                [float(x) for x in parts]
            except ValueError:
                raise InputError(f"broken {what} line {r.strip()!r}: expected {width} numbers", path, ln) from None
        raise
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr).all(axis=1))[0])
        raise InputError(f"non-finite {what} coordinate", path, first_line[bad])
    big = np.abs(arr) > MAX_COORDINATE
    if big.any():
        bad = int(np.flatnonzero(big.any(axis=1))[0])
        raise InputError(f"implausible {what} coordinate {arr[bad].tolist()} (beyond +-{MAX_COORDINATE:g} "
                         "mesh units): damaged file?", path, first_line[bad])
    return arr


def _obj_lines(path: str | Path) -> tuple[Path, list[str]]:
    path = require_file(path, "mesh")
    try:
        return path, path.read_text().splitlines()
    except UnicodeDecodeError:
        raise InputError("not a text OBJ file", path) from None


def read_obj(path: str | Path, require_faces: bool = False) -> Mesh:
    """Read an OBJ file keeping vertex order; raise :class:`InputError` naming file and line.

    Parameters
    ----------
    path : str or Path
    require_faces : bool
        Raise when the file has no faces.
    """
    path, lines = _obj_lines(path)
    v_rows, v_ln, vt_rows, vt_ln = [], [], [], []
    polygons, polygon_uvs = [], []
    groups: dict[str, list[int]] = {}
    materials: dict[str, list[int]] = {}
    current: list[int] | None = None
    current_mtl: list[int] | None = None
    mtllibs: list[str] = []
    face_lines = []
    for ln, line in enumerate(lines, start=1):
        if line.startswith("v "):
            v_rows.append(line)
            v_ln.append(ln)
        elif line.startswith("vt "):
            vt_rows.append(line)
            vt_ln.append(ln)
        elif line.startswith("f "):
            face_lines.append((ln, line))
            if current is not None:
                current.append(len(face_lines) - 1)
            if current_mtl is not None:
                current_mtl.append(len(face_lines) - 1)
        elif line.startswith("usemtl"):
            current_mtl = materials.setdefault(line[6:].strip() or "default", [])
        elif line.startswith("mtllib "):
            mtllibs += line[7:].split()
        elif line.startswith("g ") or line.strip() == "g":
            name = line[1:].strip() or "default"
            current = groups.setdefault(name, [])
    if not v_rows:
        raise InputError("no vertices ('v x y z' lines): not an OBJ mesh", path)
    vertices = _floats(v_rows, path, v_ln, 3, "vertex")
    uvs = _floats(vt_rows, path, vt_ln, 2, "texture") if vt_rows else np.zeros((0, 2))
    nv, nt = len(vertices), len(uvs)
    for ln, line in face_lines:
        items = line.split()[1:]
        try:
            vi = [int(it.split("/")[0]) for it in items]
            ti = [int(it.split("/")[1]) if it.count("/") >= 1 and it.split("/")[1] else 0 for it in items]
        except ValueError:
            raise InputError(f"broken face line {line.strip()!r}", path, ln) from None
        if len(vi) < 3:
            raise InputError(f"face with {len(vi)} vertices (need at least 3)", path, ln)
        if any(not -nv <= i <= nv or i == 0 for i in vi):       # before numpy: no int64 overflow
            raise InputError(f"face names a vertex outside 1..{nv}", path, ln)
        if any(not -nt <= i <= nt for i in ti):
            raise InputError(f"face names a texture coordinate outside 1..{nt}", path, ln)
        polygons.append(_zero_based(vi, nv, "a vertex", path, ln))
        polygon_uvs.append(_zero_based(ti, nt, "a texture coordinate", path, ln) if all(ti) else None)
    if require_faces and not polygons:
        raise InputError("mesh has no faces ('f' lines)", path)
    return Mesh(vertices, polygons, uvs, polygon_uvs, {k: np.array(v, dtype=np.intp) for k, v in groups.items()},
                {k: np.array(v, dtype=np.intp) for k, v in materials.items() if v},
                _material_colours([path.parent / m for m in mtllibs]))


def _zero_based(indices: list[int], n: int, what: str, path: Path, ln: int) -> np.ndarray:
    """A face's one-based (or negative, from the end) OBJ indices, zero-based and checked."""
    a = np.array([i - 1 if i > 0 else n + i for i in indices], dtype=np.intp)
    if a.min() < 0 or a.max() >= n:
        raise InputError(f"face names {what} outside 1..{n}", path, ln)
    return a


def _material_colours(files) -> dict:
    """``Kd`` of every ``newmtl`` in the given .mtl files that exist (others are skipped)."""
    out, name = {}, None
    for mtl in (Path(f) for f in files if Path(f).is_file()):
        for line in mtl.read_text(errors="replace").splitlines():
            parts = line.split()
            if len(parts) >= 2 and parts[0] == "newmtl":
                name = " ".join(parts[1:])
            elif len(parts) >= 4 and parts[0] == "Kd" and name is not None:
                with contextlib.suppress(ValueError):
                    out[name] = tuple(float(x) for x in parts[1:4])
    return out


def read_obj_vertices(path: str | Path, n_vertices: int | None = None) -> np.ndarray:
    """Read only the vertex positions of an OBJ (fast path for blendshape targets).

    Raises :class:`InputError` when ``n_vertices`` is given and differs.
    """
    path, lines = _obj_lines(path)
    rows = [(ln, l) for ln, l in enumerate(lines, start=1) if l.startswith("v ")]
    if not rows:
        raise InputError("no vertices ('v x y z' lines): not an OBJ mesh", path)
    v = _floats([l for _, l in rows], path, [ln for ln, _ in rows], 3, "vertex")
    if n_vertices is not None and len(v) != n_vertices:
        raise InputError(f"{len(v)} vertices, expected {n_vertices} (targets must share one topology)", path)
    return v


def _rows(fmt: str, a: np.ndarray) -> str:
    """``fmt % row`` for every row of ``a``, joined by new lines (one C-level format for all rows)."""
    a = np.asarray(a)
    return ((fmt + "\n") * len(a) % tuple(a.ravel().tolist()))[:-1] if len(a) else ""


def _face_lines(mesh: Mesh) -> str:
    """The ``g``/``f`` lines of ``mesh`` (one-based indices; ``v/vt`` where the face has UVs): runs of
    faces of one size, with or without UVs, between group changes are formatted at once."""
    polys = mesh.polygons
    uvs = mesh.polygon_uvs or [None] * len(polys)
    n = min(len(polys), len(uvs))
    if n == 0:
        return ""
    names = list(mesh.groups)
    gi = np.full(n, -1)
    for j, faces in enumerate(mesh.groups.values()):    # a face in several groups: the last one's
        f = np.asarray(faces, dtype=np.int64)
        gi[f[(f >= 0) & (f < n)]] = j
    # a "g" line where a face's group differs from the last group named (faces of no group name none)
    named = np.flatnonzero(gi >= 0)
    g_at = named[np.r_[True, gi[named][1:] != gi[named][:-1]]] if len(named) else named
    size = np.fromiter((len(p) for p in polys[:n]), dtype=np.int64, count=n)
    has_uv = np.fromiter((t is not None for t in uvs[:n]), dtype=bool, count=n)
    cut = np.flatnonzero(np.r_[True, (size[1:] != size[:-1]) | (has_uv[1:] != has_uv[:-1])])
    starts = np.union1d(cut, g_at)
    g_set = set(g_at.tolist())
    lines = []
    for s, e in zip(starts.tolist(), [*starts[1:].tolist(), n]):
        if s in g_set:
            lines.append(f"g {names[gi[s]]}")
        k = int(size[s])
        idx = np.asarray(polys[s:e], dtype=np.int64).reshape(e - s, k) + 1
        if has_uv[s]:
            t = np.asarray(uvs[s:e], dtype=np.int64).reshape(e - s, k) + 1
            lines.append(_rows("f" + " %d/%d" * k, np.stack([idx, t], axis=2).reshape(e - s, 2 * k)))
        else:
            lines.append(_rows("f" + " %d" * k if k else "f ", idx))
    return "\n".join(lines)


def write_obj(path: str | Path, mesh: Mesh, vertices: np.ndarray | None = None) -> None:
    """Write ``mesh`` (optionally with other ``vertices`` of the same count) atomically."""
    v = mesh.vertices if vertices is None else np.asarray(vertices, dtype=np.float64)
    if v.shape != mesh.vertices.shape:
        raise InputError(f"vertices: expected shape {mesh.vertices.shape}, got {v.shape}", path)
    out = ["# written by keyshape", _rows("v %.6f %.6f %.6f", v)]
    if len(mesh.uvs):
        out.append(_rows("vt %.6f %.6f", mesh.uvs))
    flines = _face_lines(mesh)
    if flines:
        out.append(flines)
    with atomic_write(path) as f:
        f.write("\n".join(out) + "\n")
