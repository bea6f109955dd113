"""A small vectorised z-buffer rasteriser (numpy only): the synthetic 3D head (:mod:`keyshape.data_synth.face3d`)
and the triangles a rig preview can ever show (:class:`keyshape.retarget.output.preview.RigRenderer`).

Per triangle the covered pixel rows, per row the covered span of pixel centres (where all three
barycentric weights, affine in the pixel, are >= 0), then every pixel of every span at once
(``np.repeat`` over the counts); the depth, affine in the pixel too, goes through a z-buffer
(``np.minimum.at``) and the nearest sample of each pixel is kept. There is no loop over triangles
or pixels. The caller gets, for every covered pixel, the winning triangle and its barycentric
coordinates, and shades it itself (interpolated vertex attributes, procedural colours).

Conventions: pixel centres at integer coordinates (OpenCV's, as the ``.pts`` labels and the tracks
CSV), x to the right, y down; smaller depth is nearer. Depth is interpolated linearly in screen
space (exact enough for the z-test on triangles a few pixels wide).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Fragments:
    """The visible sample of every covered pixel.

    Attributes
    ----------
    pixel : (n,) int64 flat pixel index ``y * width + x``
    triangle : (n,) int64 index into the triangles given to :func:`rasterize`
    bary : (n, 3) float32 barycentric coordinates of the pixel centre in that triangle
    """

    pixel: np.ndarray
    triangle: np.ndarray
    bary: np.ndarray


def rasterize(xy: np.ndarray, depth: np.ndarray, triangles: np.ndarray, width: int, height: int,
              cull: bool = True) -> Fragments:
    """Visible fragments of a triangle mesh projected to the image.

    Parameters
    ----------
    xy : (n_vertices, 2) image positions (pixels, centres at integers)
    depth : (n_vertices,) distance along the view axis (smaller is nearer)
    triangles : (n_triangles, 3) vertex indices
    width, height : image size
    cull : drop triangles seen from the back (clockwise on the screen, y down, for a mesh whose
        front faces are counter-clockwise seen from outside)

    Returns
    -------
    Fragments, one per covered pixel (the nearest sample).
    """
    xy = np.asarray(xy, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    empty = Fragments(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.float32))
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    # signed area (image y down: a front face, counter-clockwise in a y-up view, has negative area here)
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    keep = area < -1e-12 if cull else np.abs(area) > 1e-12
    lo = np.minimum(np.minimum(a, b), c)
    hi = np.maximum(np.maximum(a, b), c)
    y0 = np.maximum(np.ceil(lo[:, 1]), 0).astype(np.int64)
    y1 = np.minimum(np.floor(hi[:, 1]), height - 1).astype(np.int64)
    keep &= (y1 >= y0) & (hi[:, 0] >= 0) & (lo[:, 0] <= width - 1)
    keep &= np.floor(hi[:, 0]) >= np.ceil(lo[:, 0])
    ids = np.flatnonzero(keep)
    if not len(ids):
        return empty
    a, b, c, area, y0, y1 = a[ids], b[ids], c[ids], area[ids], y0[ids], y1[ids]
    x0 = np.maximum(np.ceil(lo[ids, 0]), 0)
    x1 = np.minimum(np.floor(hi[ids, 0]), width - 1)

    # barycentric weight of a vertex is an affine function of the pixel: w = A x + B y + C
    def edge(p, q):
        return (p[:, 1] - q[:, 1]) / area, (q[:, 0] - p[:, 0]) / area, (p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]) / area
    Aa, Ba, Ca = edge(b, c)                            # weight of a: area(p, b, c) / area(a, b, c)
    Ab, Bb, Cb = edge(c, a)
    Ac, Bc, Cc = edge(a, b)
    da, db, dc = (depth[tri[ids, k]] for k in range(3))
    Dx = da * Aa + db * Ab + dc * Ac                   # depth is affine in the pixel too
    Dy = da * Ba + db * Bb + dc * Bc
    D0 = da * Ca + db * Cb + dc * Cc
    # one row of pixels per (triangle, covered row): its span of x where all three weights are >= 0
    ny = y1 - y0 + 1
    rt = np.repeat(np.arange(len(ids)), ny)
    ry = (np.arange(len(rt)) - np.repeat(np.cumsum(ny) - ny, ny) + y0[rt]).astype(np.float64)
    lower = x0[rt].copy()
    upper = x1[rt].copy()
    for A, B, C in ((Aa, Ba, Ca), (Ab, Bb, Cb), (Ac, Bc, Cc)):
        At = A[rt]
        k = B[rt] * ry + C[rt]                        # weight = At * x + k
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = -k / At
        pos, neg = At > 1e-15, At < -1e-15
        lower = np.where(pos, np.maximum(lower, np.ceil(bound - 1e-9)), lower)
        upper = np.where(neg, np.minimum(upper, np.floor(bound + 1e-9)), upper)
        upper = np.where(~pos & ~neg & (k < -1e-9), -1.0, upper)
    count = np.maximum(upper - lower + 1, 0).astype(np.int64)
    rows = np.flatnonzero(count)
    if not len(rows):
        return empty
    rt, ry, lower, count = rt[rows], ry[rows], lower[rows], count[rows]
    drow = Dy[rt] * ry + D0[rt]
    # every pixel of every span
    pr = np.repeat(np.arange(len(rows)), count)
    px = np.arange(len(pr)) - np.repeat(np.cumsum(count) - count, count) + lower[pr]
    d = Dx[rt[pr]] * px + drow[pr]
    pix = ry[pr].astype(np.int64) * width + px.astype(np.int64)
    zbuf = np.full(width * height, np.inf)
    np.minimum.at(zbuf, pix, d)
    win = np.flatnonzero(d <= zbuf[pix])
    pix, pr, px = pix[win], pr[win], px[win]
    # exact depth ties (rare: shared edges at the same depth): keep one fragment per pixel
    if len(pix) and np.bincount(pix).max() > 1:
        _, first = np.unique(pix, return_index=True)
        pix, pr, px = pix[first], pr[first], px[first]
    t = rt[pr]
    y = ry[pr]
    wa = Aa[t] * px + Ba[t] * y + Ca[t]
    wb = Ab[t] * px + Bb[t] * y + Cb[t]
    bary = np.stack([wa, wb, 1.0 - wa - wb], 1).astype(np.float32)
    return Fragments(pix, ids[t], bary)
