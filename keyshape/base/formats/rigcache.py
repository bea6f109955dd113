"""The parsed-rig cache file (``.npz``): a blendshape rig's arrays as parsing its OBJ files gives them.

Parsing ICT-FaceKit's 54 OBJ files (26,719 vertices each) takes seconds; reading this file takes
a few hundredths. One file per rig, named by a sha256 over the content of the rig's files (see
:func:`keyshape.retarget.rig.model.load_rig`), so an edited shape is a different file and a stale
cache is never read. Layout (``np.savez``, no pickles)::

    format      "keyshape-rig-cache", version 1
    names       (n_shapes,) str                 shape names in order
    neutral     (n_vertices, 3) float64
    deltas      (n_shapes, n_vertices, 3) float64   shape - neutral
    poly_index  (n_polygons + 1,) int64         offsets of each polygon into poly_flat
    poly_flat   (n,) int64                      vertex indices of every polygon
    uvs         (n_uvs, 2) float64
    puv_index   (n_polygons + 1,) int64, puv_flat (m,) int64, puv_none (n_polygons,) bool
    groups, materials, material_colours   JSON strings

The reader trusts nothing: a file of another layout, with arrays of the wrong shape, indices out of
range or values that are not finite raises :class:`~keyshape.base.errors.InputError` (the caller then
parses the OBJ files again and rewrites the cache).
"""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.files import atomic_path
from keyshape.base.formats.obj import Mesh

FORMAT = "keyshape-rig-cache"


def _ragged(arrays) -> tuple[np.ndarray, np.ndarray]:
    lens = np.array([len(a) for a in arrays], dtype=np.int64)
    index = np.concatenate([[0], np.cumsum(lens)]).astype(np.int64)
    flat = np.concatenate([np.asarray(a, dtype=np.int64) for a in arrays]) if len(arrays) else np.zeros(0, np.int64)
    return index, flat


def write_rig_cache(path: str | Path, names: list[str], neutral: np.ndarray, deltas: np.ndarray, mesh: Mesh) -> None:
    """Write the cache file atomically (a reader never sees half of it)."""
    pi, pf = _ragged(mesh.polygons)
    puv = list(mesh.polygon_uvs) if mesh.polygon_uvs else [None] * len(mesh.polygons)
    none = np.array([p is None for p in puv], dtype=bool)
    ui, uf = _ragged([np.zeros(0, np.int64) if p is None else p for p in puv])
    as_json = lambda d: json.dumps({k: np.asarray(v).tolist() for k, v in d.items()})  # noqa: E731
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, format=np.array(FORMAT), version=np.array(1), names=np.array(list(names), dtype=str),
                     neutral=np.asarray(neutral, np.float64), deltas=np.asarray(deltas, np.float64),
                     poly_index=pi, poly_flat=pf, uvs=np.asarray(mesh.uvs, np.float64).reshape(-1, 2),
                     puv_index=ui, puv_flat=uf, puv_none=none, groups=np.array(as_json(mesh.groups)),
                     materials=np.array(as_json(mesh.materials)),
                     material_colours=np.array(json.dumps({k: list(v) for k, v in mesh.material_colours.items()})))


def read_rig_cache(path: str | Path, with_mesh: bool = True) -> tuple[list[str], np.ndarray, np.ndarray, Mesh | None]:
    """``(names, neutral, deltas, mesh)`` from a cache file, every array checked (``mesh`` None without
    ``with_mesh``: the polygons are then checked but not built).

    Raises
    ------
    InputError
        The file is missing, not a rig cache, or damaged (naming what is wrong).
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as d:
            if str(d["format"]) != FORMAT or int(d["version"]) != 1:
                raise InputError("not a keyshape rig cache", path)
            names = [str(n) for n in d["names"]]
            neutral, deltas = d["neutral"], d["deltas"]
            pi, pf, uvs = d["poly_index"], d["poly_flat"], d["uvs"]
            ui, uf, none = d["puv_index"], d["puv_flat"], d["puv_none"]
            groups, materials = json.loads(str(d["groups"])), json.loads(str(d["materials"]))
            colours = json.loads(str(d["material_colours"]))
    except InputError:
        raise
    except (OSError, KeyError, ValueError, TypeError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"unreadable rig cache ({exc})", path) from None
    nv = len(neutral)
    n_poly = len(pi) - 1
    checks = [
        (neutral.ndim == 2 and neutral.shape[1:] == (3,) and neutral.dtype == np.float64, "neutral shape"),
        (deltas.shape == (len(names), nv, 3) and deltas.dtype == np.float64, "deltas shape"),
        (bool(np.isfinite(neutral).all()) and bool(np.isfinite(deltas).all()), "finite values"),
        (n_poly >= 0 and pi[0] == 0 and pi[-1] == len(pf) and bool((np.diff(pi) >= 0).all()), "polygon offsets"),
        (len(pf) == 0 or (pf.min() >= 0 and pf.max() < nv), "polygon vertex indices"),
        (len(ui) == n_poly + 1 and len(none) == n_poly and ui[0] == 0 and ui[-1] == len(uf)
         and bool((np.diff(ui) >= 0).all()), "polygon uv offsets"),
        (len(uf) == 0 or (uf.min() >= 0 and uf.max() < len(uvs)), "polygon uv indices"),
        (uvs.ndim == 2 and uvs.shape[1] == 2 and bool(np.isfinite(uvs).all()), "uvs"),
        (len(set(names)) == len(names), "shape names"),
    ]
    bad = [what for ok, what in checks if not ok]
    if bad:
        raise InputError(f"damaged rig cache ({', '.join(bad)})", path)
    if not with_mesh:
        return names, neutral, deltas, None
    polygons = [pf[pi[i]:pi[i + 1]].astype(np.intp) for i in range(n_poly)]
    puv = [None if none[i] else uf[ui[i]:ui[i + 1]].astype(np.intp) for i in range(n_poly)]
    try:
        mesh = Mesh(neutral, polygons, uvs, puv, {k: np.asarray(v, dtype=np.intp) for k, v in groups.items()},
                    {k: np.asarray(v, dtype=np.intp) for k, v in materials.items()},
                    {k: tuple(float(x) for x in v) for k, v in colours.items()})
    except (TypeError, ValueError) as exc:
        raise InputError(f"damaged rig cache ({exc})", path) from None
    return names, neutral, deltas, mesh
