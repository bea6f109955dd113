"""A test rig of another topology made from ICT-FaceKit, whose true landmarks are known by construction
(bench/rig_landmarks_accuracy.py and the tests of the rig landmarks).

:func:`remesh` decimates a rig's mesh by edge collapses: each pass collapses a random set of edges
whose stars do not touch (so the collapses are independent), each edge's two vertices merged into one
new vertex at a random point along the edge (30-70%), its shape deltas interpolated alike (the shapes
carried across exactly: the new vertex moves as the surface point it sits on); an edge is collapsed
only when the link condition holds (the mesh stays a manifold with the same holes: the mouth slit, the
eyes) and no triangle around it flips. Vertices given as ``keep`` (the landmarks' own) are never
collapsed, so the landmarks' true vertices on the new mesh are known; the surviving vertices are then
shuffled, so that nothing of ICT-FaceKit's vertex order is left.

:func:`remeshed_ict_rig` writes such a rig from the shipped ICT-FaceKit subset (the face skin,
``retarget/data/ict_face.npz``, no eyeballs): ``neutral.obj`` and one OBJ per expression, the true
contours48 landmarks beside it and the iBUG-68 vertex list as a rig would publish it, in centimetres
and Y-up, or (``units="m"``, ``up="z"``) in metres with Z up and the face towards -Y (Blender's front).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import scipy.sparse as sp


def _edges(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges (n_edges, 2) sorted within, and how many triangles each borders."""
    e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    u, counts = np.unique(e, axis=0, return_counts=True)
    return u, counts


def _normals(v: np.ndarray, tri: np.ndarray) -> np.ndarray:
    n = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def _collapse_pass(v, d, tri, keep, rng):
    n = len(v)
    edges, count = _edges(tri)
    adj = sp.coo_matrix((np.ones(2 * len(edges)), (edges.ravel(), edges[:, ::-1].ravel())), shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    bnd_v = np.zeros(n, bool)
    bnd_v[edges[count == 1].ravel()] = True
    a, b = edges[:, 0], edges[:, 1]
    ok = ~keep[a] & ~keep[b] & (count <= 2)
    ok &= np.where(count == 1, True, ~bnd_v[a] & ~bnd_v[b])                # a boundary edge, or an interior one
    common = np.asarray(adj[a].multiply(adj[b]).sum(axis=1)).ravel()      # link condition
    ok &= common == count
    cand = rng.permutation(np.flatnonzero(ok))
    locked = np.zeros(n, bool)
    chosen = []
    indptr, indices = adj.indptr, adj.indices
    for k in cand:                                                        # a greedy set of non-touching stars
        i, j = a[k], b[k]
        ring = np.concatenate([indices[indptr[i]:indptr[i + 1]], indices[indptr[j]:indptr[j + 1]], [i, j]])
        if locked[ring].any():
            continue
        locked[ring] = True
        chosen.append(k)
    chosen = np.asarray(chosen, np.intp)
    if not len(chosen):
        return v, d, tri, keep, 0
    t = rng.uniform(0.3, 0.7, len(chosen))
    i, j = a[chosen], b[chosen]
    nv = v.copy()
    nv[i] = (1 - t)[:, None] * v[i] + t[:, None] * v[j]
    remap = np.arange(n)
    remap[j] = i
    new_tri = remap[tri]
    alive = (new_tri[:, 0] != new_tri[:, 1]) & (new_tri[:, 1] != new_tri[:, 2]) & (new_tri[:, 2] != new_tri[:, 0])
    flip = alive & (np.einsum("ij,ij->i", _normals(v, tri), _normals(nv, new_tri)) < 0.5)
    bad = np.zeros(n, bool)
    bad[tri[flip].ravel()] = True
    good = ~(bad[i] | bad[j])                                            # those collapses are left out
    i, j, t = i[good], j[good], t[good]
    v = v.copy()
    d = d.copy()
    v[i] = (1 - t)[:, None] * v[i] + t[:, None] * v[j]
    d[:, i] = (1 - t)[None, :, None] * d[:, i] + t[None, :, None] * d[:, j]
    remap = np.arange(n)
    remap[j] = i
    tri = remap[tri]
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 2] != tri[:, 0])]
    return v, d, tri, keep, len(i)


def remesh(neutral: np.ndarray, deltas: np.ndarray, triangles: np.ndarray, keep: np.ndarray,
           fraction: float = 0.4, seed: int = 0):
    """Decimate a rig to about ``fraction`` of its vertices (see the module docstring).

    Parameters
    ----------
    neutral : (n_vertices, 3); deltas : (n_shapes, n_vertices, 3); triangles : (n_triangles, 3)
    keep : indices of vertices never collapsed (they keep their positions and deltas)
    fraction : the share of vertices to keep (about)
    seed : the random collapses' and the new order's seed

    Returns
    -------
    neutral, deltas, triangles of the new mesh, and ``new_index`` (n_vertices,): each old vertex's
    index in the new mesh (-1 for collapsed ones).
    """
    rng = np.random.default_rng(seed)
    v, d, tri = np.asarray(neutral, np.float64), np.asarray(deltas, np.float64), np.asarray(triangles, np.intp)
    kp = np.zeros(len(v), bool)
    kp[np.asarray(keep, np.intp)] = True
    for _ in range(40):
        used = np.unique(tri)
        if len(used) <= fraction * len(neutral):
            break
        v, d, tri, kp, done = _collapse_pass(v, d, tri, kp, rng)
        if not done:
            break
    used = np.unique(tri)
    order = rng.permutation(used)                                         # new vertex k is old vertex order[k]
    new_index = np.full(len(neutral), -1)
    new_index[order] = np.arange(len(order))
    return v[order], d[:, order], new_index[tri], new_index


def reshape_face(vertices: np.ndarray, amount: float, seed: int = 0) -> np.ndarray:
    """Another face from ICT-FaceKit's: a face ``1 + amount / 10`` times wider and ``1 - amount / 20`` as
    tall, plus a smooth random displacement (eight Gaussian bumps 2.5 cm wide) of up to ``amount`` cm."""
    rng = np.random.default_rng(seed + 1000)
    v = np.asarray(vertices, np.float64)
    c = v.mean(axis=0)
    out = c + (v - c) * [1 + amount / 10, 1 - amount / 20, 1.0]
    centres = v[rng.choice(len(v), 8, replace=False)]
    amp = rng.uniform(-amount, amount, (8, 3))
    g = np.exp(-0.5 * (np.linalg.norm(v[:, None] - centres[None], axis=-1) / 2.5) ** 2)
    return out + g @ amp


def restyle_shapes(vertices: np.ndarray, deltas: np.ndarray, amount: float, seed: int = 0) -> np.ndarray:
    """Another artist's shapes: each shape's deltas scaled by a smooth random factor over the face
    (``exp`` of ``amount / 4`` times a field of four Gaussian bumps 3 cm wide: 0.8-1.25 for 1 cm)."""
    rng = np.random.default_rng(seed + 2000)
    v = np.asarray(vertices, np.float64)
    centres = v[rng.choice(len(v), (len(deltas), 4))]                    # (n_shapes, 4, 3)
    g = np.exp(-0.5 * (np.linalg.norm(v[None, :, None] - centres[:, None], axis=-1) / 3.0) ** 2)
    f = np.exp(amount / 4 * np.einsum("svc,sc->sv", g, rng.uniform(-1, 1, (len(deltas), 4))))
    return deltas * f[..., None]


def remeshed_ict_rig(folder: str | Path, fraction: float = 0.4, seed: int = 0, units: str = "cm",
                     up: str = "y", names=None, reshape: float = 0.0, mask: bool = False, arkit: bool = False) -> dict:
    """Write a remeshed rig from the shipped ICT-FaceKit subset into ``folder`` (see the module docstring).

    ``reshape`` (cm, default 0): another face's proportions (:func:`reshape_face`) and another artist's
    shapes (:func:`restyle_shapes`): the automatic landmarks then cannot rely on ICT-FaceKit's face.
    ``mask``: only the face's front is kept (forehead to chin, ear to ear less the ears, as ARKit's face
    mesh), no back of the head, neck or ears. ``arkit``: the shapes named as ARKit names them
    (``eyeBlinkLeft`` for ``eyeBlink_L``), one ``browInnerUp`` (both sides').

    Returns ``{"rig": folder, "landmarks": the true contours48 file, "ibug68": the published-style list
    (one index a line), "scale": mesh units per ICT centimetre, "rotation": (3, 3) the rig's axes from ICT's}``.
    """
    from keyshape.base.formats.obj import Mesh, write_obj
    from keyshape.base.formats.poses import write_rig_landmarks
    from keyshape.retarget.targets.demo import load_expressions
    from keyshape.retarget.rig.landmarks import contours48_from_ibug68, one_hot

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ex = load_expressions()
    W = contours48_from_ibug68(one_hot(ex.landmarks, len(ex.neutral)), ex.neutral).W
    keep = np.unique(np.concatenate([np.flatnonzero(W.any(axis=0)), ex.landmarks]))
    v, d, tri, new_index = remesh(ex.neutral, ex.deltas, ex.triangles, keep, fraction, seed)
    if reshape:
        d = restyle_shapes(v, d, reshape, seed)
        v = reshape_face(v, reshape, seed)
    ibug = new_index[ex.landmarks]
    if mask:                                                              # the face's front only (ARKit's mesh)
        c = ex.neutral[ex.landmarks].mean(axis=0)
        inside = (np.abs(v[:, 0] - c[0]) < 7.0) & (v[:, 1] > c[1] - 7.0) & (v[:, 1] < c[1] + 6.0) & (v[:, 2] > c[2] - 3.5)
        inside |= np.linalg.norm(v[:, None] - v[ibug][None], axis=-1).min(axis=1) < 1.0    # the jaw line too
        tri = tri[inside[tri].all(axis=1)]
        used = np.unique(tri)
        remap = np.full(len(v), -1)
        remap[used] = np.arange(len(used))
        v, d, tri, ibug = v[used], d[:, used], remap[tri], remap[ibug]
    W = contours48_from_ibug68(one_hot(ibug, len(v)), v).W                # no eyeballs: pupils between corners
    scale = {"cm": 1.0, "m": 0.01}[units]
    rot = {"y": np.eye(3), "z": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])}[up]   # z-up: front to -y
    v = scale * v @ rot.T
    d = scale * d @ rot.T
    mesh = Mesh(v, list(tri))
    write_obj(folder / "neutral.obj", mesh)
    shapes = dict(zip(ex.names, d))
    if arkit:                                     # ARKit's spelling, one browInnerUp
        shapes["browInnerUp"] = shapes.pop("browInnerUp_L") + shapes.pop("browInnerUp_R")
        shapes = {n[:-2] + ("Left" if n.endswith("_L") else "Right") if n[-2:] in ("_L", "_R") else n: x
                  for n, x in shapes.items()}
    for n, x in shapes.items():
        if names is None or n in names:
            write_obj(folder / f"{n}.obj", mesh, v + x)
    points = []
    for row in W:
        nz = np.flatnonzero(row)
        points.append(int(nz[0]) if len(nz) == 1 else [[int(k), float(row[k])] for k in nz])
    lm = folder.parent / f"{folder.name}_landmarks.json"
    write_rig_landmarks(lm, "contours48", len(v), points)
    ib = folder.parent / f"{folder.name}_ibug68.txt"
    ib.write_text("".join(f"{int(k)}\n" for k in ibug))
    (folder.parent / f"{folder.name}_truth.json").write_text(json.dumps({"scale": scale, "rotation": rot.tolist()}))
    return {"rig": folder, "landmarks": lm, "ibug68": ib, "scale": scale, "rotation": rot}
