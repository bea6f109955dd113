"""Checks and small geometry on triangle meshes: validation, edges, components, closest points on triangles."""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from keyshape.base.errors import InputError


def check_mesh(vertices: np.ndarray, triangles: np.ndarray, name: str = "mesh", area_eps: float = 1e-12):
    """Validate a triangle mesh; raise :class:`InputError` naming ``name`` and the first bad face.

    Refuses: no faces, faces naming missing vertices, degenerate faces (a
    repeated vertex or an area below ``area_eps`` times the squared bounding
    box diagonal) and non-manifold edges (shared by more than two faces).
    Returns (vertices float64, triangles intp).
    """
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise InputError(f"{name}: expected vertices (n_vertices, 3), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise InputError(f"{name}: non-finite vertex coordinates")
    if t.size == 0:
        raise InputError(f"{name}: mesh has no faces; registration needs a surface")
    t = t.astype(np.intp)
    if t.ndim != 2 or t.shape[1] != 3:
        raise InputError(f"{name}: expected triangles (n_faces, 3), got {t.shape}")
    if t.min() < 0 or t.max() >= len(v):
        bad = int(np.flatnonzero((t < 0).any(1) | (t >= len(v)).any(1))[0])
        raise InputError(f"{name}: face {bad} names a vertex outside 0..{len(v) - 1}")
    rep = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2])
    diag2 = float(np.sum((v.max(0) - v.min(0)) ** 2)) or 1.0
    area2 = np.sum(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]) ** 2, axis=1)
    bad = rep | (area2 <= (area_eps * diag2) ** 2)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"{name}: {int(bad.sum())} degenerate face(s) (repeated vertex or zero area), "
                         f"first is face {i} with vertices {t[i].tolist()}")
    e, _, counts = edges(t)
    if counts.max() > 2:
        i = int(np.argmax(counts))
        raise InputError(f"{name}: non-manifold mesh: edge {e[i].tolist()} is shared by {counts[i]} faces "
                         f"({int((counts > 2).sum())} such edges)")
    return v, t


def edges(triangles: np.ndarray):
    """Unique undirected edges (n_edges, 2), the inverse map of the 3 n_faces half-edges, and face counts."""
    h = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    e, inv, counts = np.unique(np.sort(h, axis=1), axis=0, return_inverse=True, return_counts=True)
    return e, inv.ravel(), counts


def interior_edge_faces(triangles: np.ndarray):
    """(n_interior, 2) face pairs sharing an edge, and (n_interior, 2) that edge's vertices."""
    e, inv, counts = edges(triangles)
    nf = len(triangles)
    face_of = np.tile(np.arange(nf), 3)
    order = np.argsort(inv, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    two = np.flatnonzero(counts == 2)
    f1 = face_of[order[starts[two]]]
    f2 = face_of[order[starts[two] + 1]]
    return np.stack([f1, f2], 1), e[two]


def component_of(n_vertices: int, triangles: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Boolean mask of vertices connected (through faces) to any of ``seeds``."""
    a = np.concatenate([triangles[:, 0], triangles[:, 1], triangles[:, 2]])
    b = np.concatenate([triangles[:, 1], triangles[:, 2], triangles[:, 0]])
    g = coo_matrix((np.ones(len(a)), (a, b)), shape=(n_vertices, n_vertices))
    _, labels = connected_components(g, directed=False)
    return np.isin(labels, np.unique(labels[np.asarray(seeds, np.intp)]))


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points to ``p`` on triangles ``(a, b, c)``, all (..., 3), vectorised (Ericson, RTCD 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("...i,...i", ab, ap)
    d2 = np.einsum("...i,...i", ac, ap)
    bp = p - b
    d3 = np.einsum("...i,...i", ab, bp)
    d4 = np.einsum("...i,...i", ac, bp)
    cp = p - c
    d5 = np.einsum("...i,...i", ab, cp)
    d6 = np.einsum("...i,...i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        out = a + ab * v[..., None] + ac * w[..., None]  # interior
        # edges
        t_ab = d1 / (d1 - d3)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out = np.where(m[..., None], a + ab * t_ab[..., None], out)
        t_ac = d2 / (d2 - d6)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out = np.where(m[..., None], a + ac * t_ac[..., None], out)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        out = np.where(m[..., None], b + (c - b) * t_bc[..., None], out)
    # vertices
    out = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, out)
    out = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, out)
    return out


class TriangleSurface:
    """Closest points on a triangle surface (the target's faces for E_dist of eq. 17).

    Candidate triangles are the ``k`` whose centroids are nearest (KD-tree),
    then the exact closest point on each candidate is taken: exact whenever
    the closest triangle is among them, which holds for dense, well-shaped
    meshes and points near the surface (the registration's case).
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, k: int = 6):
        self.vertices = np.asarray(vertices, np.float64)
        self.triangles = np.asarray(triangles, np.intp)
        self.k = min(k, len(self.triangles))
        self._abc = self.vertices[self.triangles]  # (n_faces, 3, 3)
        self._tree = cKDTree(self._abc.mean(1))

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(closest points (n, 3), face index (n,)) for ``points`` (n, 3)."""
        p = np.asarray(points, np.float64)
        _, cand = self._tree.query(p, k=self.k)
        cand = cand.reshape(len(p), self.k)
        abc = self._abc[cand]  # (n, k, 3, 3)
        q = closest_on_triangles(p[:, None], abc[..., 0, :], abc[..., 1, :], abc[..., 2, :])
        d = np.sum((q - p[:, None]) ** 2, axis=2)
        j = np.argmin(d, axis=1)
        r = np.arange(len(p))
        return q[r, j], cand[r, j]
