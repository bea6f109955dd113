"""Image warping: Delaunay triangulation, piecewise-affine warps and morphing.

Design notes and figures: docs/synth.md, "Notes on the code", ``keyshape/base/warp.py``.
"""
from __future__ import annotations

import cv2
import numpy as np


def triangulate(points: np.ndarray) -> np.ndarray:
    """Delaunay triangles ``(n_triangles, 3)`` of ``points`` (n, 2)."""
    from scipy.spatial import Delaunay          # imported when first needed (training; not ``keyshape track``)

    return Delaunay(np.asarray(points, np.float64)).simplices.astype(np.intp)


class PiecewiseAffine:
    """Piecewise-affine warp defined on a fixed destination triangulation.

    Built once for a destination shape on an ``(height, width)`` grid: every
    pixel's triangle and barycentric coordinates are precomputed, so each warp
    is one ``cv2.remap`` of the source image whatever the source shape.

    Parameters
    ----------
    dst_points : (n, 2)
        Vertices in the output image (pixels).
    triangles : (n_triangles, 3)
        Triangulation of the vertices.
    shape : (height, width)
        Output grid.

    Notes
    -----
    A pixel ``p`` inside triangle ``(a, b, c)`` of the destination has
    barycentric weights ``λ`` with ``p = λ_a d_a + λ_b d_b + λ_c d_c``; it
    samples the source at ``λ_a s_a + λ_b s_b + λ_c s_c``, which is the affine
    map of that triangle. Pixels outside every triangle use the nearest
    triangle's affine map (extrapolation), so the warp is defined everywhere.
    """

    def __init__(self, dst_points: np.ndarray, triangles: np.ndarray, shape: tuple[int, int]):
        dst = np.asarray(dst_points, np.float64)
        self.triangles = np.asarray(triangles, np.intp)
        self.shape = (int(shape[0]), int(shape[1]))
        h, w = self.shape
        # triangle of every pixel by rasterising the triangles (last drawn wins on shared edges)
        label = np.zeros((h, w), np.int32)
        for k, tri in enumerate(self.triangles):
            cv2.fillConvexPoly(label, np.round(dst[tri] * 16).astype(np.int32), k + 1, cv2.LINE_8, 4)
        label = label.ravel() - 1
        yy, xx = np.mgrid[0:h, 0:w]
        pix = np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float64)
        miss = np.flatnonzero(label < 0)
        self.inside = label >= 0
        if len(miss):   # outside every triangle: the nearest triangle (by centroid) extrapolates
            cen = dst[self.triangles].mean(1)
            label[miss] = np.argmin(((pix[miss, None, :] - cen[None]) ** 2).sum(-1), axis=1)
        t = dst[self.triangles[label]]                            # (n_pix, 3, 2)
        m = np.stack([t[:, 0] - t[:, 2], t[:, 1] - t[:, 2]], axis=2)   # (n_pix, 2, 2)
        det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        rel = pix - t[:, 2]
        l0 = (m[:, 1, 1] * rel[:, 0] - m[:, 0, 1] * rel[:, 1]) / det
        l1 = (-m[:, 1, 0] * rel[:, 0] + m[:, 0, 0] * rel[:, 1]) / det
        self.tri_index = label
        self.bary = np.stack([l0, l1, 1 - l0 - l1], axis=1)     # (n_pix, 3)

    def map_coords(self, src_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Source sampling maps ``(map_x, map_y)`` float32 of the output grid for ``src_points``."""
        s = np.asarray(src_points, np.float64)[self.triangles[self.tri_index]]   # (n_pix, 3, 2)
        xy = np.einsum("pk,pkc->pc", self.bary, s)
        h, w = self.shape
        return xy[:, 0].reshape(h, w).astype(np.float32), xy[:, 1].reshape(h, w).astype(np.float32)

    def __call__(self, image: np.ndarray, src_points: np.ndarray) -> np.ndarray:
        """Warp ``image`` so that ``src_points`` land on the destination vertices."""
        mx, my = self.map_coords(src_points)
        return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def morph(image_a: np.ndarray, shape_a: np.ndarray, image_b: np.ndarray, shape_b: np.ndarray,
          alpha: float, triangles: np.ndarray, out_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Image morph between two (pre-warped) images (Beier-Neely style, piecewise-affine).

    The intermediate shape is ``(1 - alpha) shape_a + alpha shape_b``; both
    images are warped to it and cross-dissolved with the same weight.

    Returns
    -------
    image : float32 (out_shape)
    shape : (n_points, 2)
    """
    shape = (1 - alpha) * np.asarray(shape_a, np.float64) + alpha * np.asarray(shape_b, np.float64)
    pwa = PiecewiseAffine(shape, triangles, out_shape)
    wa = pwa(np.asarray(image_a, np.float32), shape_a)
    wb = pwa(np.asarray(image_b, np.float32), shape_b)
    return (1 - alpha) * wa + alpha * wb, shape
