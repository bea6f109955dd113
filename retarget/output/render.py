"""Orthographic software render of a mesh with Lambert shading (for previews).

No OpenGL: every triangle's bounding-box pixels are enumerated at once
(``np.repeat`` over per-triangle pixel counts), barycentric coordinates decide
coverage, and a z-buffer keeps the nearest sample per pixel (stable sort by
depth, first occurrence per pixel). Shading is Lambert with per-vertex normals
interpolated across triangles, from a light near the viewer.

Conventions: the mesh is viewed along -z (camera on +z looking at the origin),
x right and y up in the mesh become x right and y down in the image.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.geometry import vertex_normals


@dataclass
class OrthoCamera:
    """Maps mesh (x, y) to pixel (column, row): ``col = (x - x0) * scale``, ``row = (y0 - y) * scale``."""

    x0: float
    y0: float
    scale: float
    width: int
    height: int

    @classmethod
    def fit(cls, vertices: np.ndarray, width: int = 320, height: int = 320, margin: float = 0.05) -> "OrthoCamera":
        """Frame ``vertices`` (any (..., 3) array, e.g. all frames) with a relative ``margin``."""
        v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
        span = np.maximum(hi - lo, 1e-12)
        scale = min(width / span[0], height / span[1]) * (1 - 2 * margin)
        cx, cy = (lo + hi) / 2
        return cls(cx - width / 2 / scale, cy + height / 2 / scale, float(scale), int(width), int(height))

    def project(self, vertices: np.ndarray) -> np.ndarray:
        """(n, 3) -> (n, 3): pixel column, pixel row, depth (larger z is nearer)."""
        v = np.asarray(vertices, dtype=np.float64)
        return np.stack([(v[:, 0] - self.x0) * self.scale, (self.y0 - v[:, 1]) * self.scale, v[:, 2]], axis=1)


def render(vertices: np.ndarray, triangles: np.ndarray, camera: OrthoCamera,
           colour=(200, 190, 180), background=(40, 40, 40), light=(0.3, 0.4, 1.0),
           ambient: float = 0.15) -> np.ndarray:
    """Render one frame: (height, width, 3) BGR uint8.

    Parameters
    ----------
    vertices : (n_vertices, 3)
    triangles : (n_triangles, 3) vertex indices
    camera : :class:`OrthoCamera`
    colour, background : BGR of the surface and background
    light : direction towards the light (normalised here)
    ambient : ambient term added to ``max(n . l, 0)``
    """
    v = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.intp)
    if v.ndim != 2 or v.shape[1] != 3 or tri.ndim != 2 or tri.shape[1] != 3:
        raise InputError(f"render: expected (n_vertices, 3) and (n_triangles, 3), got {v.shape}, {tri.shape}")
    w, h = camera.width, camera.height
    image = np.empty((h, w, 3), np.uint8)
    image[:] = background
    p = camera.project(v)
    nrm = vertex_normals(v, tri)
    a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    # pixel centres at integer + 0.5
    lo = np.floor(np.minimum(np.minimum(a, b), c)[:, :2] - 0.5).astype(np.int64) + 1
    hi = np.floor(np.maximum(np.maximum(a, b), c)[:, :2] - 0.5).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [w - 1, h - 1])
    nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    keep = np.flatnonzero((nx > 0) & (ny > 0) & (np.abs(area) > 1e-12))
    if keep.size == 0:
        return image
    counts = nx[keep] * ny[keep]
    t = np.repeat(keep, counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    px = lo[t, 0] + local % nx[t] + 0.5
    py = lo[t, 1] + local // nx[t] + 0.5
    ax, ay, bx, by, cx, cy = a[t, 0], a[t, 1], b[t, 0], b[t, 1], c[t, 0], c[t, 1]
    inv = 1.0 / area[t]
    l1 = ((cx - bx) * (py - by) - (cy - by) * (px - bx)) * inv
    l2 = ((ax - cx) * (py - cy) - (ay - cy) * (px - cx)) * inv
    l3 = 1.0 - l1 - l2
    inside = (l1 >= 0) & (l2 >= 0) & (l3 >= 0)
    t, px, py, l1, l2, l3 = t[inside], px[inside], py[inside], l1[inside], l2[inside], l3[inside]
    depth = l1 * a[t, 2] + l2 * b[t, 2] + l3 * c[t, 2]
    pix = (py.astype(np.int64)) * w + px.astype(np.int64)
    order = np.argsort(-depth, kind="stable")            # nearest (largest z) first
    _, first = np.unique(pix[order], return_index=True)
    sel = order[first]
    n = (l1[sel, None] * nrm[tri[t[sel], 0]] + l2[sel, None] * nrm[tri[t[sel], 1]]
         + l3[sel, None] * nrm[tri[t[sel], 2]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    li = np.asarray(light, dtype=np.float64)
    li = li / np.linalg.norm(li)
    shade = np.clip(np.abs(n @ li) * (1 - ambient) + ambient, 0, 1)   # two-sided
    flat = image.reshape(-1, 3)
    flat[pix[sel]] = np.clip(shade[:, None] * np.asarray(colour, dtype=np.float64), 0, 255).astype(np.uint8)
    return image


def render_frames(frames: np.ndarray, triangles: np.ndarray, size=(320, 320), camera: OrthoCamera | None = None,
                  **kw):
    """Yield a rendered BGR image per frame of ``frames`` (n_frames, n_vertices, 3), all with one
    camera (default: framing every 50th frame, so the face does not jump between frames)."""
    f = np.asarray(frames)
    cam = camera or OrthoCamera.fit(f[:: max(1, len(f) // 50)], *size)
    for v in f:
        yield render(v, triangles, cam, **kw)


def side_by_side(left: np.ndarray, right: np.ndarray, gap: int = 4, background=(40, 40, 40)) -> np.ndarray:
    """One BGR image: ``left`` (e.g. the source frame with contours) | ``right`` (the rendered target),
    ``right`` scaled to ``left``'s height (``cv2.resize``), separated by ``gap`` background pixels."""
    import cv2
    a = left if left.ndim == 3 else cv2.cvtColor(left, cv2.COLOR_GRAY2BGR)
    b = right if right.ndim == 3 else cv2.cvtColor(right, cv2.COLOR_GRAY2BGR)
    h = a.shape[0]
    if b.shape[0] != h:
        b = cv2.resize(b, (max(1, round(b.shape[1] * h / b.shape[0])), h), interpolation=cv2.INTER_AREA)
    mid = np.empty((h, gap, 3), np.uint8)
    mid[:] = background
    return np.concatenate([a, mid, b], axis=1)
