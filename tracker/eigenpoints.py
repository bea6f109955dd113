"""Covell's eigen-points appearance model: coupled PCA of face intensities and landmarks.

Section 3 of 004_119ba07521a9af0b.txt (after Covell 1996): labelled frames have
their affine motion removed (warped into a common *model frame*), the set is
enlarged by image morphing between pairs, and PCA is run on vectors stacking
the normalised intensities of the model-frame face region and the landmark
coordinates. A new (pre-warped) image is projected on the basis using the
intensity rows only; the same coefficients give its landmarks.

Model-frame coordinates are pixels of a square ``patch_size`` x ``patch_size``
image; ``image_from_model`` affines (2, 3) map them to video pixels.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from keyshape.base.errors import InputError, NotFittedError
from keyshape.base.formats.model import ModelFile, read_model, write_model
from keyshape.base.schemes import Scheme, load_scheme
from keyshape.base.geometry import apply_affine, fit_affine, invert_affine, procrustes_mean
from keyshape.base.warp import morph, triangulate



# --------------------------------------------------------------------------- sampling

def to_gray(image: np.ndarray) -> np.ndarray:
    """``uint8`` single-channel view of a BGR or gray frame."""
    image = np.asarray(image)
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2:
        raise InputError(f"frame: expected (height, width) or (height, width, 3), got {image.shape}")
    return image


def level_sizes(h: int, w: int, levels: int = 4) -> list[tuple[int, int]]:
    """``(height, width)`` of each level of a :class:`Pyramid` of an ``h`` x ``w`` frame, finest first: at most
    ``levels``, each ``cv2.pyrDown``'s of the one before, down to the first under 64 pixels a side."""
    sizes = [(h, w)]
    while len(sizes) < levels and min(h, w) >= 64:
        h, w = (h + 1) // 2, (w + 1) // 2
        sizes.append((h, w))
    return sizes


class Pyramid:
    """Gaussian pyramid (``cv2.pyrDown``) of a frame, finest first, built lazily on access.

    ``image`` is a gray frame or a BGR one (converted to gray when first needed).
    :meth:`window` serves a window of a level without building the whole level:
    the tracker only looks at the face, so per frame it converts and
    downsamples a crop around it (the same pixel values as the full level).
    """

    _PAD = 12      # level pixels added around the first region asked for (later iterations move a little)

    def __init__(self, image: np.ndarray, levels: int = 4):
        image = np.asarray(image)
        if image.ndim not in (2, 3):
            raise InputError(f"frame: expected (height, width) or (height, width, 3), got {image.shape}")
        self._src = image
        self._levels = [image] if image.ndim == 2 else []
        self._regions: dict = {}
        self._sizes = level_sizes(*image.shape[:2], levels)
        self.n_levels = len(self._sizes)

    def __len__(self) -> int:
        return self.n_levels

    @property
    def size(self) -> tuple[int, int]:
        """``(height, width)`` of the finest level."""
        return self._sizes[0]

    def __getitem__(self, level: int) -> np.ndarray:
        if not self._levels:
            self._levels.append(to_gray(self._src))
        while len(self._levels) <= level:
            self._levels.append(cv2.pyrDown(self._levels[-1]))
        return self._levels[level]

    def window(self, level: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """An image of ``self[level]``'s size whose pixels ``[x0, x1) x [y0, y1)`` equal ``self[level]``'s.

        When that level is not built yet, only a crop of the source around the
        window (aligned to ``2**level``, with a margin wider than the smoothing
        kernels reach, padded for the next few requests) is converted and
        downsampled, into an uninitialised full-size buffer: the pixels outside
        the crop are undefined. Sampling with the unchanged coordinates keeps
        the results bit-identical to using the full level.
        """
        if len(self._levels) > level:
            return self._levels[level]
        h, w = self._sizes[level]
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        got = self._regions.get(level)
        if got is not None and got[1] <= x0 and got[2] <= y0 and x1 <= got[3] and y1 <= got[4]:
            return got[0]
        if got is not None or x0 >= x1 or y0 >= y1:      # moved out of the crop, or off the image
            return self[level]
        p = self._PAD
        rx0, ry0, rx1, ry1 = max(x0 - p, 0), max(y0 - p, 0), min(x1 + p, w), min(y1 + p, h)
        s, m = 2 ** level, 4     # pyrDown's 5-tap kernel disturbs at most 2 pixels of a crop's edge per level
        H, W = self._sizes[0]
        sx0, sy0 = max(rx0 - m, 0) * s, max(ry0 - m, 0) * s
        sx1, sy1 = min((rx1 + m) * s, W), min((ry1 + m) * s, H)
        img = self._levels[0][sy0:sy1, sx0:sx1] if self._levels else to_gray(self._src[sy0:sy1, sx0:sx1])
        for _ in range(level):
            img = cv2.pyrDown(img)
        ox, oy = sx0 // s, sy0 // s
        buf = np.empty((h, w), np.uint8)
        buf[ry0:ry1, rx0:rx1] = img[ry0 - oy:ry1 - oy, rx0 - ox:rx1 - ox]
        self._regions[level] = (buf, rx0, ry0, rx1, ry1)
        return buf


def warp_patch(pyramid: Pyramid, image_from_model: np.ndarray, size: int) -> np.ndarray:
    """Sample the ``size`` x ``size`` model-frame patch of a frame (float32).

    The pyramid level is chosen so that one model pixel covers at most about
    1.5 source pixels (anti-aliasing without per-frame blurring). Pixel
    centres of pyramid level ``l`` sit at ``(x_0 + 0.5) / 2**l - 0.5``.
    """
    return warp_patch_u8(pyramid, image_from_model, size).astype(np.float32)


def warp_patch_u8(pyramid: Pyramid, image_from_model: np.ndarray, size) -> np.ndarray:
    """:func:`warp_patch` before the float conversion: the ``uint8`` patch (same values).

    ``size`` is an int (square patch) or ``(width, height)``.
    """
    sw, sh = (size, size) if isinstance(size, (int, np.integer)) else (int(size[0]), int(size[1]))
    a = np.asarray(image_from_model, np.float64)
    return warp_level(pyramid, pyramid_level(pyramid, a), a.tolist(), sw, sh)


def pyramid_level(pyramid: Pyramid, image_from_model: np.ndarray) -> int:
    """The pyramid level :func:`warp_patch_u8` samples for an affine (one model pixel covers at
    most about 1.5 source pixels); it depends on the linear part only."""
    (a00, a01, _), (a10, a11, _) = image_from_model.tolist()
    scale = math.sqrt(abs(a00 * a11 - a01 * a10))
    if scale > 1.5:
        return min(max(int(math.floor(math.log2(scale / 1.5))) + 1, 0), len(pyramid) - 1)
    return 0


def warp_level(pyramid: Pyramid, lvl: int, image_from_model: list, sw: int, sh: int) -> np.ndarray:
    """:func:`warp_patch_u8` at a given level ``lvl``, the affine as nested lists of floats
    ``[[a00, a01, a02], [a10, a11, a12]]`` (the tracker's per-region loop calls it directly)."""
    (a00, a01, a02), (a10, a11, a12) = image_from_model
    if lvl:
        f = 0.5 ** lvl
        d = 0.5 * f - 0.5
        a00, a01, a02, a10, a11, a12 = a00 * f, a01 * f, a02 * f + d, a10 * f, a11 * f, a12 * f + d
    # sample only the window the patch covers (bilinear reads one pixel beyond; 2 for safety): the
    # corners (-1, -1) to (sw, sh), x = a02 + a00 u + a01 v, each term's extremes taken apart
    u0, u1, v0, v1 = -a00, a00 * sw, -a01, a01 * sh
    x0 = a02 + (u0 if u0 < u1 else u1) + (v0 if v0 < v1 else v1)
    x1 = a02 + (u1 if u0 < u1 else u0) + (v1 if v0 < v1 else v0)
    u0, u1, v0, v1 = -a10, a10 * sw, -a11, a11 * sh
    y0 = a12 + (u0 if u0 < u1 else u1) + (v0 if v0 < v1 else v1)
    y1 = a12 + (u1 if u0 < u1 else u0) + (v1 if v0 < v1 else v0)
    # within 1e7 of the origin (a NaN or an infinity among the coefficients fails one of the tests); a patch
    # beyond it is no view of this image, and cv2.warpAffine kills the process on such coefficients (1e30,
    # an infinity: seen with OpenCV 5.1), so it is a blank patch (the tracker's residual then calls the frame lost)
    if not (-1e7 < x0 and x1 < 1e7 and -1e7 < y0 and y1 < 1e7):
        return np.zeros((sh, sw), np.uint8)
    img = pyramid.window(lvl, math.floor(x0) - 2, math.floor(y0) - 2, math.ceil(x1) + 3, math.ceil(y1) + 3)
    return cv2.warpAffine(img, np.array([[a00, a01, a02], [a10, a11, a12]]), (sw, sh),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)


def normalise(values: np.ndarray) -> np.ndarray:
    """Zero mean, unit variance along the last axis (per-frame lighting normalisation)."""
    v = np.asarray(values, np.float64)
    v = v - v.mean(axis=-1, keepdims=True)
    sd = v.std(axis=-1, keepdims=True)
    return v / np.maximum(sd, 1e-6)


def shift_patch(patch: np.ndarray, shift) -> np.ndarray:
    """A model-frame patch sampled at ``x + shift`` (bilinear, border replicated): the content moves
    by ``-shift``, so a feature at ``p + shift`` lands at ``p``."""
    dx, dy = float(shift[0]), float(shift[1])
    return cv2.warpAffine(patch, np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]]), patch.shape[::-1],
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)


def _pca_rows(xc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Principal axes (rows, orthonormal) and their variances of centred rows ``xc`` (n, d), n << d.

    Uses the n x n Gram matrix (``xc xc^T = V Λ V^T`` gives axes ``Λ^{-1/2} V^T xc``),
    the same axes as an SVD of ``xc`` at a fraction of the cost when n << d. BLAS runs on the calling
    thread: training calls it a hundred times on small matrices, where a thread pool's threads only spin
    (measured in ``docs/benchmarks.md``).
    """
    from threadpoolctl import threadpool_limits      # training only

    with threadpool_limits(1):
        g = xc @ xc.T
        lam, v = np.linalg.eigh(g)
    order = np.argsort(lam)[::-1]
    lam, v = lam[order], v[:, order]
    keep = lam > lam[0] * 1e-10 if len(lam) and lam[0] > 0 else np.zeros(len(lam), bool)
    lam, v = lam[keep], v[:, keep]
    axes = (v.T @ xc) / np.sqrt(lam)[:, None]
    return axes, lam


def _held_out_residuals(intens: np.ndarray, src_of: np.ndarray, n_labels: int, k: int) -> list[float]:
    """Leave-one-label-out residual of each labelled frame (the scale of "normal" appearance error when
    tracking): the mean square of its intensities ``intens[i]`` off the ``k`` principal axes of the samples not
    made from it (``src_of``: the two labels each sample was morphed from)."""
    res = []
    for i in range(n_labels):                     # a dozen or so labels, each its own small PCA
        keep = (src_of[:, 0] != i) & (src_of[:, 1] != i)
        xi = intens[keep]
        mu = xi.mean(0)
        vt = _pca_rows(xi - mu)[0][:k]
        e = intens[i] - mu
        e = e - vt.T @ (vt @ e)
        res.append(float(e @ e / len(e)))
    return res


def _hull_mask(points: np.ndarray, size: int, grow: int) -> np.ndarray:
    """``uint8`` mask (size, size) of the convex hull of ``points`` (rounded), dilated by ``grow`` pixels."""
    mask = np.zeros((size, size), np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.round(points).astype(np.int32)), 1)
    return cv2.dilate(mask, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))


def _coupled(intens: np.ndarray, land: np.ndarray, weight: float) -> tuple[float, np.ndarray]:
    """The eigen-points coupling: the landmark rows' scale (their total variance ``weight`` times the
    intensity rows') and the stacked vectors ``[intens, land * scale]``."""
    scale = float(np.sqrt(weight * intens.var(0).sum() / max(land.var(0).sum(), 1e-12)))
    return scale, np.hstack([intens, land * scale])


def _reading_operators(components, mean, n_pix: int, landmark_scale: float, variance, residuals, ridge: float):
    """``(U_I, pinv_I, mean_I, mean_L, U_L)`` of coupled eigenvectors ``components`` (rows) and their ``mean``:
    the intensity rows, the coefficients' operator, and the landmark rows unscaled. With ``ridge > 0``
    ``pinv_I`` is the MAP estimate under the PCA prior ``c_j ~ N(0, λ_j)`` and pixel noise ``σ²`` (``ridge``
    times the median leave-one-out residual), ``(U_IᵀU_I + σ²Λ⁻¹)⁻¹U_Iᵀ``: the prior stops components whose
    intensity rows are nearly dependent from amplifying noise; 0: the paper's plain least squares."""
    ui = components[:, :n_pix].T                                      # (n_pix, k)
    if ridge > 0:
        sigma2 = ridge * float(np.median(residuals))
        pinv = np.linalg.solve(ui.T @ ui + np.diag(sigma2 / np.maximum(variance, 1e-12)), ui.T)
    else:
        pinv = np.linalg.pinv(ui)
    return ui, pinv, mean[:n_pix], mean[n_pix:] / landmark_scale, components[:, n_pix:].T / landmark_scale


# --------------------------------------------------------------------------- the model

def region_groups(scheme: Scheme) -> dict[str, np.ndarray]:
    """Point groups read by their own region models: each eye (with its pupil), each brow, the mouth."""
    groups: dict[str, list[int]] = {}
    for name, idx in scheme.contours.items():
        side = "left" if "left" in name else "right" if "right" in name else ""
        if name.startswith(("eye", "pupil")) and side:
            key = f"eye_{side}"
        elif name.startswith("brow") and side:
            key = f"brow_{side}"
        elif name.startswith("lip"):
            key = "mouth"
        elif name == "nose":                   # the auxiliary nose points (Scheme.auxiliary)
            key = "nose"
        else:
            continue
        groups.setdefault(key, []).extend(int(i) for i in idx)
    out = {k: np.array(sorted(set(v)), np.intp) for k, v in groups.items() if len(set(v)) >= 2}
    return out


def split_upper_lower(points: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a region's points (a lip or eye outline) into upper and lower halves, corners in both.

    The corners are the leftmost and rightmost points in the model frame's
    reference shape; points above the line joining them are upper.
    """
    pts = np.asarray(points, np.intp)
    xy = ref[pts]
    left, right = int(np.argmin(xy[:, 0])), int(np.argmax(xy[:, 0]))
    a, b = xy[left], xy[right]
    side = (b[0] - a[0]) * (xy[:, 1] - a[1]) - (b[1] - a[1]) * (xy[:, 0] - a[0])   # > 0: below (y down)
    corner = np.zeros(len(pts), bool)
    corner[[left, right]] = True
    return pts[corner | (side < 0)], pts[corner | (side > 0)]


class RegionModel:
    """Eigen-points model of one facial region inside the global model frame.

    Coupled PCA of the region's normalised intensities (a dilated hull of its points, sampled in the
    region's bounding ``box``) and its points, over the global model's training patches; the tracker
    refines the region's translation first (:meth:`keyshape.tracker.fitting.Tracker.read_regions`).

    ``box`` is ``(x0, y0, width, height)`` in model pixels, ``index`` the flat
    indices of the region's pixels in that box. ``centred``: trained on crops that follow the
    region's centroid (``AppearanceModel(centre_eyes=True)``), so its box must be placed where
    the feature is (the tracker aligns it; :meth:`AppearanceModel.predict` starts it at the global
    reading's centroid).
    """

    ARRAYS = ("points", "box", "index", "mean", "components", "variance", "train_residuals")

    def __init__(self, name: str, points, box, index, mean, components, variance, train_residuals, landmark_scale,
                 centred: bool = False):
        self.name = name
        self.centred = bool(centred)
        self.points = np.asarray(points, np.intp)
        self.box = np.asarray(box, np.intp)
        self.index = np.asarray(index, np.intp)
        self.mean = np.asarray(mean, np.float64)
        self.components = np.asarray(components, np.float64)
        self.variance = np.asarray(variance, np.float64)
        self.train_residuals = np.asarray(train_residuals, np.float64)
        self.landmark_scale = float(landmark_scale)

    @classmethod
    def fit_region(cls, name, points, ref, patches, shapes, src_of, n_labels, model):
        """Region ``name`` (its ``points``) fitted to the training samples; ``model``: the
        :class:`AppearanceModel` being fitted, whose parameters give the region's variance kept, landmark
        weight, border and centring."""
        variance, landmark_weight, n_components = model._variance(name), model.landmark_weight, model.n_components
        grow = max(2, int(round(model.face_width * model._grow(name))))
        centre = model.centre_eyes and name.startswith("eye")
        size = patches.shape[-1]
        if centre:
            # each sample's crop follows the region's centroid and its points keep their place in the box:
            # the appearance model no longer has to read the feature's translation (a linear reading shrinks
            # it toward the labelled frames' mean), the tracker's alignment of the box reads it
            d = shapes[:, points].mean(1) - ref[points].mean(0)
            patches = np.stack([shift_patch(p, v) for p, v in zip(patches, d)])
            shapes = shapes.copy()
            shapes[:, points] -= d[:, None]
        mask = _hull_mask(ref[points], size, grow)
        x0, y0, w, h = cv2.boundingRect(mask)
        mask = mask.astype(bool)[y0:y0 + h, x0:x0 + w]
        index = np.flatnonzero(mask.ravel())
        crops = patches[:, y0:y0 + h, x0:x0 + w]
        intens = normalise(crops.reshape(len(crops), -1)[:, index])
        land = shapes[:, points].reshape(len(shapes), -1)
        scale, x = _coupled(intens, land, landmark_weight)
        mean = x.mean(0)
        vt, var = _pca_rows(x - mean)
        ratio = var / max(var.sum(), 1e-300)
        k = int(np.searchsorted(np.cumsum(ratio), variance) + 1) if n_components is None else int(n_components)
        k = min(k, max(1, len(x) - 1), len(vt))
        res = _held_out_residuals(intens, src_of, n_labels, k)
        return cls(name, points, (x0, y0, w, h), index, mean, vt[:k], var[:k] / len(x), res, scale, centre)

    def precompute(self, ridge: float) -> None:
        n_pix = len(self.index)
        ui, self.pinv_i, self.mean_i, self.mean_l, ul = _reading_operators(
            self.components, self.mean, n_pix, self.landmark_scale, self.variance, self.train_residuals, ridge)
        self.ul = np.ascontiguousarray(ul)
        q, _ = np.linalg.qr(np.hstack([np.ones((n_pix, 1)), ui]))
        self.qt = np.ascontiguousarray(q.T)
        self.n_pix = n_pix
        # the lips' stretch and tilt (Tracker.read_regions): the box centre's x, and each pixel's x from it
        self.box_cx = (int(self.box[2]) - 1) / 2.0
        self.box_xc = (self.index % int(self.box[2])).astype(np.float64) - self.box_cx

    def crop(self, patch: np.ndarray) -> np.ndarray:
        """The region's box of a model-frame patch (size, size)."""
        x0, y0, w, h = (int(v) for v in self.box)
        return patch[y0:y0 + h, x0:x0 + w]

    def error(self, box_patch: np.ndarray) -> tuple[np.ndarray, float]:
        """Normalised intensity error (n_pix,) of a box patch and its contrast (std) before normalising."""
        v = box_patch.ravel()[self.index].astype(np.float64)
        e = v - v.sum() / self.n_pix
        sd = max(math.sqrt(float(e @ e) / self.n_pix), 1e-6)
        e *= 1.0 / sd
        e -= self.mean_i
        return e, sd

    def read(self, box_patch: np.ndarray) -> np.ndarray:
        """Model-frame points ``(len(points), 2)`` of the region from its box patch (box coordinates = model)."""
        e, _ = self.error(box_patch)
        return (self.mean_l + self.ul @ (self.pinv_i @ e)).reshape(-1, 2)


class ShapeRefiner:
    """A region's shape fitted to the frame by analysis by synthesis (a project-out active appearance model,
    Matthews and Baker 2004; menpofit's fitters), after the eigen-points reading (docs/tracker.md, "The lips'
    shape fitted to the frame").

    Trained on the labelled frames: the shape model is the PCA of the region's points in the model frame (plus
    the two translations); the appearance, the frames' normalised grey levels in a template over the mean shape
    (a grid of ``step`` model pixels inside the triangulation of the points and of a ring ``ring`` times their
    hull), its mean ``a0`` and principal components, projected out. Per frame
    (:func:`keyshape.tracker.kernels.refine_shape`) the shape moves from the reading by Gauss-Newton steps under a
    Gaussian prior on its components. ``write``: the points whose refined positions replace the reading.
    """

    ARRAYS = ("points", "write", "ext", "tri", "bary", "s0", "basis", "weights", "a0", "qt")

    def __init__(self, points, write, ext, tri, bary, s0, basis, weights, a0, qt):
        self.points = np.asarray(points, np.intp)
        self.write = np.asarray(write, np.intp)
        self.ext = np.ascontiguousarray(ext, np.float64)
        self.tri = np.ascontiguousarray(tri, np.intp)
        self.bary = np.ascontiguousarray(bary, np.float64)
        self.s0 = np.ascontiguousarray(s0, np.float64)
        self.basis = np.ascontiguousarray(basis, np.float64)
        self.weights = np.ascontiguousarray(weights, np.float64)
        self.a0 = np.ascontiguousarray(a0, np.float64)
        self.qt = np.ascontiguousarray(qt, np.float64)

    @classmethod
    def fit(cls, points, write, pyramids, poses, shapes, step=0.5, ring=1.3, variance=0.98, appearance=0.95,
            prior=16.0):
        """Train from the labelled frames.

        Parameters
        ----------
        points : the region's point indices (all the scheme's lip points)
        write : the points whose fitted positions replace the reading (a subset of ``points``)
        pyramids : the labelled frames' :class:`Pyramid`
        poses : (n, 2, 3) their ``image_from_model`` affines
        shapes : (n, n_points, 2) their points in the model frame
        step : the template's grid spacing (model pixels)
        ring : the outer ring's size over the points' hull, about their centroid
        variance, appearance : fractions of the shape's and of the appearance's variance kept
        prior : the prior's weight (times the pixel noise over each shape component's variance)

        Returns
        -------
        ShapeRefiner
        """
        from scipy.spatial import Delaunay          # training only
        from keyshape.tracker.kernels import sample_shape

        pts = np.asarray(points, np.intp)
        m = len(pts)
        sh = np.asarray(shapes, np.float64)[:, pts]
        s0 = sh.mean(0)
        hull = cv2.convexHull(s0.astype(np.float32), returnPoints=False).ravel()
        ext = np.zeros((m + len(hull), m))
        ext[:m] = np.eye(m)
        ext[m + np.arange(len(hull)), hull] += ring
        ext[m:] -= (ring - 1) / m                  # the ring: ring x (hull point - centroid) + centroid
        v0 = ext @ s0
        tri = Delaunay(v0)
        lo, hi = v0.min(0), v0.max(0)
        gx, gy = np.meshgrid(np.arange(lo[0], hi[0], step), np.arange(lo[1], hi[1], step))
        grid = np.column_stack([gx.ravel(), gy.ravel()])
        simp = tri.find_simplex(grid)
        grid, simp = grid[simp >= 0], simp[simp >= 0]
        t = tri.transform[simp]
        b = np.einsum("nij,nj->ni", t[:, :2], grid - t[:, 2])
        tri_i, bary = tri.simplices[simp].astype(np.intp), np.column_stack([b, 1 - b.sum(1)])
        x = (sh - s0).reshape(len(sh), -1)
        _, sv, vt = np.linalg.svd(x, full_matrices=False)
        lam = sv ** 2 / len(sh)
        k = min(int(np.searchsorted(np.cumsum(lam) / max(lam.sum(), 1e-300), variance) + 1), len(lam))
        basis, lam = vt[:k].T, lam[:k]
        for tr in (np.tile([1.0, 0.0], m), np.tile([0.0, 1.0], m)):   # the region's translation, weak prior
            tr = tr - basis @ (basis.T @ tr)
            if np.linalg.norm(tr) > 1e-3:
                basis = np.column_stack([basis, tr / np.linalg.norm(tr)])
                lam = np.append(lam, 4.0)                    # 2 model pixels
        n_pix = len(grid)
        a = np.empty((len(sh), n_pix))
        vx, gx, gy = np.empty((len(ext), 2)), np.empty(n_pix), np.empty(n_pix)
        for i, (pyr, pose, shp) in enumerate(zip(pyramids, poses, sh)):
            img, f, at = cls.image(pyr, np.asarray(pose, np.float64), shp)
            sample_shape(img, f, at, (tri_i, bary, ext), shp.ravel().copy(), (vx, a[i], gx, gy))
        a = normalise(a)
        a0 = a.mean(0)
        ax, va = _pca_rows(a - a0)
        ka = min(int(np.searchsorted(np.cumsum(va) / max(va.sum(), 1e-300), appearance) + 1), len(va))
        q, _ = np.linalg.qr(np.column_stack([np.ones(n_pix), ax[:ka].T]))
        res = _held_out_residuals(a, np.repeat(np.arange(len(a))[:, None], 2, 1), len(a), ka)   # the pixel noise
        weights = prior * float(np.median(res)) / np.maximum(lam, 1e-12)
        return cls(pts, write, ext, tri_i, bary, s0.ravel(), basis, weights, a0, q.T)

    #: the Gaussian blur (pixels of the level sampled) of the crop the shape is fitted on
    BLUR = 1.0
    #: its kernel: cv2.GaussianBlur's for float32 images (4 sigmas either side, float32 weights), so the
    #: uint8 crop is blurred into float32 in one call with the values of converting it first
    _GAUSS = cv2.getGaussianKernel(int(round(8 * BLUR + 1)) | 1, BLUR, cv2.CV_32F)

    @staticmethod
    def level(pyr: Pyramid, pose: np.ndarray) -> tuple[int, float]:
        """The pyramid level a shape is fitted on, one finer than :func:`pyramid_level`'s (about one source pixel
        per model pixel), and its scale."""
        lvl = max(pyramid_level(pyr, pose) - 1, 0)
        return lvl, 0.5 ** lvl

    @classmethod
    def image(cls, pyr: Pyramid, pose: np.ndarray, shape: np.ndarray):
        """The image a shape near ``shape`` (model frame, (m, 2)) is fitted on: a crop of :meth:`level`'s pyramid
        level, blurred by ``BLUR``,
        around the shape's points (60% of their extent and 4 pixels beyond). Returns ``(crop, f, pose6)``:
        the crop (:meth:`crop`), the level's scale and the pose (6,) moved to the crop's origin; None for the
        crop where the shape is not finite."""
        from keyshape.tracker.kernels import PAD, shape_box

        lvl, f = cls.level(pyr, pose)
        box = np.empty(4, np.intp)
        if not shape_box(np.asarray(pose, np.float64), np.ascontiguousarray(shape, np.float64).ravel(), f,
                         pyr._sizes[lvl], box):
            return None, f, pose.ravel()
        crop = cls.crop(pyr, lvl, box)
        at = pose.ravel().copy()
        at[2] -= (int(box[0]) - PAD) / f
        at[5] -= (int(box[1]) - PAD) / f
        return crop, f, at

    @classmethod
    def crop(cls, pyr: Pyramid, lvl: int, box: np.ndarray) -> np.ndarray:
        """Pixels ``box`` (``x0, y0, x1, y1``, :func:`~keyshape.tracker.kernels.shape_box`) of pyramid level
        ``lvl`` blurred by ``BLUR`` (in float32), as float64 with the border
        :func:`~keyshape.tracker.kernels.sample_shape` reads (:func:`~keyshape.tracker.kernels.padded`)."""
        from keyshape.tracker.kernels import padded

        x0, y0, x1, y1 = box.tolist()
        crop = pyr.window(lvl, x0, y0, x1, y1)[y0:y1, x0:x1]
        return padded(cv2.sepFilter2D(crop, cv2.CV_32F, cls._GAUSS, cls._GAUSS, borderType=cv2.BORDER_REPLICATE))

    def tables(self) -> tuple:
        """The constant arrays of :func:`~keyshape.tracker.kernels.refine_shape`."""
        g = np.zeros((len(self.tri), len(self.ext)))
        np.put_along_axis(g, self.tri, self.bary, axis=1)
        g = g @ self.ext                             # (n_pix, m): each pixel's weights of the shape's points
        gsx = np.ascontiguousarray((g @ self.basis[0::2]).T)
        gsy = np.ascontiguousarray((g @ self.basis[1::2]).T)
        return (self.tri, self.bary, self.ext, gsx, gsy, self.basis, self.s0, self.a0, self.qt, self.weights)

    def work(self) -> tuple:
        """Work arrays of :func:`~keyshape.tracker.kernels.refine_shape`, allocated once per tracker."""
        n, k, q = len(self.tri), self.basis.shape[1], len(self.qt)
        return (np.empty((len(self.ext), 2)), np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty((k, n)),
                np.empty(q),
                np.empty((q, k)), np.empty((k, k)), np.empty(k), np.empty(k), np.empty(k))


class Reading(NamedTuple):
    """Constant operators of a fitted model's reading (:attr:`AppearanceModel.reading_`).

    ``c = pinv_i @ (e - mean_i)`` are the coefficients of normalised intensities ``e``,
    ``basis_i @ c`` their intensity reconstruction and ``mean_l + basis_l @ c`` the
    model-frame landmarks (flattened ``x0, y0, x1, ...``).
    """

    mean_i: np.ndarray
    pinv_i: np.ndarray
    basis_i: np.ndarray
    mean_l: np.ndarray
    basis_l: np.ndarray


class AppearanceModel:
    """Person-specific eigen-points model (Covell 1996; section 3 of 004_119ba07521a9af0b.txt).

    Parameters
    ----------
    scheme : str or Scheme
        Landmark scheme of the labels (``contours48``, ``ibug68`` or a JSON file).
    n_components : int or None
        Number of coupled eigenvectors kept; None chooses the smallest number
        explaining ``variance`` of the training set.
    variance : float
        Fraction of variance to explain when ``n_components`` is None.
    face_width : int
        Width in model pixels of the reference shape's bounding box.
    margin : float
        Border around the reference shape, as a fraction of its size.
    n_morphs : int
        Morphed images added to the training set (pairs drawn at random,
        blend weights 1/3 and 2/3).
    ridge : float
        Strength of the Gaussian prior on the coefficients in the projection
        (0: the paper's plain least squares on the intensity rows).
    landmark_weight : float
        Total variance of the landmark rows relative to the intensity rows in
        the stacked PCA vectors (the coupling of eigen-points).
    regions : bool
        Also learn one eigen-points model per facial region (each eye with its pupil, each brow, the
        mouth: the scheme's contours ``eye_*``/``pupil_*``, ``brow_*``, ``lip_*``) on the same training set;
        each reads its own points from its own pixels (``docs/tracker.md``, "How each frame is tracked").
    split_mouth : bool
        Read the upper and the lower lip (corners in both) with separate region
        models, each with its own translation (the jaw drops the lower lip).
    region_grow : float
        Border added around each region's points (fraction of ``face_width``):
        the pixels a region model sees.
    lip_grow, brow_grow : float or None
        The same for the lip and the brow regions (None: ``region_grow``; measured in ``docs/tracker.md``).
    centre_eyes : bool
        Train the eyes' region models on crops that follow the eye's centroid, so that the tracker's
        alignment of the box reads where the eye is (off by default: ``docs/tracker.md``).
    eye_variance : float or None
        Fraction of variance the eyes' region models keep (None: ``variance``; off by default,
        ``docs/tracker.md``).
    lip_refine : bool
        Fit the lips' shape to the frame by analysis by synthesis after the reading (:class:`ShapeRefiner`;
        schemes with ``lip_outer`` and ``lip_inner`` contours). Model files written before it read as False.
    rng : None, int or Generator
        Randomness of the choice of morph pairs.

    Attributes
    ----------
    reference_ : (n_points, 2) mean shape in the model frame
    patch_size_ : int
    mask_ : (patch_size, patch_size) bool, the face region sampled
    mean_ : (n_pixels + 2 n_points,) mean stacked vector (landmark rows scaled)
    components_ : (k, n_pixels + 2 n_points) coupled eigenvectors (rows)
    explained_variance_ratio_ : (k,)
    landmark_scale_ : float, factor applied to landmark coordinates in the stacked vectors
    train_residuals_ : (n_labels,) leave-one-label-out appearance residuals of the labelled frames
    train_poses_ : (n_labels, 2, 3) ``image_from_model`` of each labelled frame
    train_shapes_ : (n_labels, n_points, 2) model-frame labels
    region_models_ : list of :class:`RegionModel` (empty when ``regions`` is False)
    lip_refiner_ : :class:`ShapeRefiner` or None (``lip_refine`` off, or no inner lips in the scheme)
    """

    def __init__(self, scheme: str | Scheme = "contours48", n_components: int | None = None,
                 variance: float = 0.98, face_width: int = 64, margin: float = 0.22, n_morphs: int = 120,
                 landmark_weight: float = 1.0, ridge: float = 1.0, regions: bool = True, split_mouth: bool = True,
                 region_grow: float = 0.1, lip_grow: float | None = 0.14, brow_grow: float | None = None,
                 centre_eyes: bool = False, eye_variance: float | None = None, lip_refine: bool = True, rng=None):
        self.scheme = scheme
        self.n_components = n_components
        self.variance = variance
        self.face_width = face_width
        self.margin = margin
        self.n_morphs = n_morphs
        self.landmark_weight = landmark_weight
        self.ridge = ridge
        self.regions = regions
        self.split_mouth = split_mouth
        self.region_grow = region_grow
        self.lip_grow = lip_grow
        self.brow_grow = brow_grow
        self.centre_eyes = centre_eyes
        self.eye_variance = eye_variance
        self.lip_refine = lip_refine
        self.rng = rng

    # ---------------------------------------------------------------- fitting
    def _scheme(self) -> Scheme:
        return self.scheme if isinstance(self.scheme, Scheme) else load_scheme(self.scheme)

    def fit(self, frames, labels: np.ndarray) -> "AppearanceModel":
        """Learn the model from labelled frames.

        Parameters
        ----------
        frames : sequence of (H, W) or (H, W, 3) uint8 images
        labels : (n_labels, n_points, 2) landmarks of those frames, image pixels

        Returns
        -------
        self
        """
        scheme = self._scheme()
        labels = scheme.check_shapes(labels, "labels")
        if labels.ndim != 3:
            raise InputError(f"labels: expected (n_labels, {scheme.n_points}, 2), got {labels.shape}")
        n = len(labels)
        if len(frames) != n:
            raise InputError(f"{len(frames)} frames but {n} label sets")
        if n < 2:
            raise InputError(f"need at least 2 labelled frames, got {n}")
        if not np.isfinite(labels).all():
            raise InputError("labels contain NaN or infinity")
        sizes = {np.asarray(f).shape[:2] for f in frames}
        if len(sizes) != 1:
            raise InputError(f"the labelled frames have different sizes {sorted(sizes)}: one video's frames expected")
        h, w = sizes.pop()
        self.image_size_ = (int(w), int(h))          # the tracker then refuses video of another size
        rng = np.random.default_rng(self.rng)

        # reference shape in the model frame (eq.: affine removal of section 3)
        mean = procrustes_mean(labels)
        lo, hi = mean.min(0), mean.max(0)
        s = self.face_width / (hi - lo)[0]
        size = int(np.ceil(self.face_width * (1 + 2 * self.margin)))
        ref = (mean - (lo + hi) / 2) * s + (size - 1) / 2.0
        ref[:, 1] += (size - 1) / 2.0 - (ref[:, 1].min() + ref[:, 1].max()) / 2.0
        self.reference_ = ref
        self.patch_size_ = size

        mask = _hull_mask(ref, size, max(1, int(round(self.face_width * 0.08)))).astype(bool)
        self.mask_ = mask
        self._index = np.flatnonzero(mask.ravel())

        pyramids = [Pyramid(to_gray(img)) for img in frames]
        poses, patches, shapes = [], [], []
        for pyr, lab in zip(pyramids, labels):
            a = fit_affine(ref, lab)
            poses.append(a)
            patches.append(warp_patch(pyr, a, size))
            shapes.append(apply_affine(invert_affine(a), lab))
        self.train_poses_ = np.stack(poses)
        self.train_shapes_ = np.stack(shapes)
        patches = np.stack(patches)

        # enlargement by morphing between pre-warped labelled images
        border = np.array([[0, 0], [size - 1, 0], [0, size - 1], [size - 1, size - 1],
                           [(size - 1) / 2, 0], [(size - 1) / 2, size - 1], [0, (size - 1) / 2],
                           [size - 1, (size - 1) / 2]], np.float64)
        tri = triangulate(np.vstack([ref, border]))
        pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)])
        m_pairs = min(len(pairs), max(self.n_morphs // 2, 0))
        chosen = pairs[rng.choice(len(pairs), m_pairs, replace=False)] if m_pairs else np.empty((0, 2), int)
        src_of = [(i, i) for i in range(n)]
        m_patches, m_shapes = [patches], [self.train_shapes_]
        for i, j in chosen:
            for alpha in (1 / 3, 2 / 3):
                img, shp = morph(patches[i], np.vstack([shapes[i], border]), patches[j],
                                 np.vstack([shapes[j], border]), alpha, tri, (size, size))
                m_patches.append(img[None])
                m_shapes.append(shp[None, :len(ref)])
                src_of.append((i, j))
        all_patches = np.concatenate(m_patches)
        all_shapes = np.concatenate(m_shapes)
        self.n_samples_ = len(all_patches)

        intens = normalise(all_patches.reshape(len(all_patches), -1)[:, self._index])
        land = all_shapes.reshape(len(all_shapes), -1)
        self.landmark_scale_, x = _coupled(intens, land, self.landmark_weight)
        self._pca(x)

        src_of = np.array(src_of)
        self.train_residuals_ = np.array(_held_out_residuals(intens, src_of, n, self.k_))
        self.scheme_ = scheme
        groups = region_groups(scheme) if self.regions else {}
        if "mouth" in groups and self.split_mouth:
            # upper and lower lip move apart (jaw drop): each gets its own translation
            groups["lip_upper"], groups["lip_lower"] = split_upper_lower(groups.pop("mouth"), ref)
        self.region_models_ = [RegionModel.fit_region(name, pts, ref, all_patches, all_shapes, src_of, n, self)
                               for name, pts in groups.items()]
        self.lip_refiner_ = None
        lips = {k: v for k, v in scheme.contours.items() if k in ("lip_outer", "lip_inner")}
        if self.lip_refine and len(lips) == 2:
            pts = sorted(set(lips["lip_outer"]) | set(lips["lip_inner"]))
            self.lip_refiner_ = ShapeRefiner.fit(pts, pts, pyramids, self.train_poses_, self.train_shapes_)
        self._precompute()
        return self

    def _variance(self, name: str) -> float:
        """Fraction of variance kept by region ``name``: ``eye_variance`` for the eyes, else ``variance``."""
        return self.eye_variance if name.startswith("eye") and self.eye_variance is not None else self.variance

    def _grow(self, name: str) -> float:
        """Border of region ``name`` (fraction of ``face_width``): ``lip_grow``, ``brow_grow`` or ``region_grow``."""
        own = self.lip_grow if name.startswith(("lip", "mouth")) else self.brow_grow if name.startswith("brow") \
            else None
        return self.region_grow if own is None else own

    def _pca(self, x: np.ndarray) -> None:
        mean = x.mean(0)
        vt, var = _pca_rows(x - mean)
        # deterministic signs (as sklearn's svd_flip): largest |loading| positive
        signs = np.sign(vt[np.arange(len(vt)), np.abs(vt).argmax(1)])
        signs[signs == 0] = 1
        vt *= signs[:, None]
        ratio = var / max(var.sum(), 1e-300)
        max_k = max(1, len(x) - 1)
        if self.n_components is None:
            k = int(np.searchsorted(np.cumsum(ratio), self.variance) + 1)
        else:
            k = int(self.n_components)
            if k < 1:
                raise InputError(f"n_components must be >= 1, got {k}")
        k = min(k, max_k)
        self.k_ = k
        self.mean_ = mean
        self.components_ = vt[:k]
        self.explained_variance_ratio_ = ratio[:k]
        self.explained_variance_ = var[:k] / len(x)

    def _precompute(self) -> None:
        """Everything constant per frame: the pseudo-inverse of the intensity rows."""
        n_pix = len(self._index)
        self._ui, self._pinv_i, self._mean_i, self._mean_l, self._ul = _reading_operators(
            self.components_, self.mean_, n_pix, self.landmark_scale_, self.explained_variance_,
            self.train_residuals_, self.ridge)
        self._n_pix = n_pix
        for rm in getattr(self, "region_models_", []):
            rm.precompute(self.ridge)

    # ---------------------------------------------------------------- use
    def _check_fitted(self) -> None:
        if not hasattr(self, "components_"):
            raise NotFittedError("this AppearanceModel is not fitted: call fit(frames, labels) or load a model")

    @property
    def n_points(self) -> int:
        self._check_fitted()
        return len(self.reference_)

    @property
    def index_(self) -> np.ndarray:
        """Flat indices of the mask pixels in the patch."""
        return self._index

    def intensities(self, patch: np.ndarray) -> np.ndarray:
        """Normalised intensity vector(s) of model-frame patch(es) (..., size, size)."""
        p = np.asarray(patch)
        return normalise(p.reshape(*p.shape[:-2], -1)[..., self._index])

    def project(self, intensities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coefficients and appearance residual of normalised intensities (..., n_pix).

        The coefficients solve ``min_c |U_I c - (v - mean_I)|`` (least squares
        on the intensity rows of the coupled eigenvectors); the residual is
        the mean squared error per pixel of that fit.
        """
        self._check_fitted()
        e = np.asarray(intensities, np.float64) - self._mean_i
        c = e @ self._pinv_i.T
        r = e - c @ self._ui.T
        return c, np.einsum("...i,...i->...", r, r) / self._n_pix

    def landmarks(self, coefficients: np.ndarray) -> np.ndarray:
        """Model-frame landmarks (..., n_points, 2) read from the coefficients (landmark rows)."""
        c = np.asarray(coefficients, np.float64)
        flat = self._mean_l + c @ self._ul.T
        return flat.reshape(*c.shape[:-1], -1, 2)

    def predict(self, frame: np.ndarray, image_from_model: np.ndarray) -> tuple[np.ndarray, float]:
        """Image landmarks ``(n_points, 2)`` and residual of ``frame`` warped by ``image_from_model``."""
        self._check_fitted()
        patch = warp_patch(Pyramid(to_gray(frame)), image_from_model, self.patch_size_)
        c, r = self.project(self.intensities(patch))
        shape = self.landmarks(c)
        glob = shape.copy()
        for rm in getattr(self, "region_models_", []):
            if rm.centred:                      # its box placed at the global reading's centroid
                d = glob[rm.points].mean(0) - self.reference_[rm.points].mean(0)
                shape[rm.points] = rm.read(rm.crop(shift_patch(patch, d))) + d
            else:
                shape[rm.points] = rm.read(rm.crop(patch))
        return apply_affine(image_from_model, shape), float(r)

    @property
    def reading_(self) -> "Reading":
        """The constant operators of :meth:`project` and :meth:`landmarks` (for a fast tracker loop)."""
        self._check_fitted()
        return Reading(self._mean_i, self._pinv_i, self._ui, self._mean_l, self._ul)

    # ---------------------------------------------------------------- persistence
    _ARRAYS = ("reference_", "mask_", "mean_", "components_", "explained_variance_ratio_", "explained_variance_",
               "train_residuals_", "train_poses_", "train_shapes_")
    #: each saved parameter's kind and range: (type, allows None, lowest, highest), bounds inclusive
    _PARAM_RANGES = {"n_components": (int, True, 1, 100_000), "variance": (float, False, 1e-6, 1.0),
                     "face_width": (int, False, 8, 4096), "margin": (float, False, 0.0, 10.0),
                     "n_morphs": (int, False, 0, 1_000_000), "landmark_weight": (float, False, 1e-9, 1e9),
                     "ridge": (float, False, 0.0, 1e9), "regions": (bool, False, None, None),
                     "split_mouth": (bool, False, None, None), "region_grow": (float, False, 0.0, 10.0),
                     "lip_grow": (float, True, 0.0, 10.0), "brow_grow": (float, True, 0.0, 10.0),
                     "centre_eyes": (bool, False, None, None), "eye_variance": (float, True, 1e-6, 1.0),
                     "lip_refine": (bool, False, None, None)}
    _PARAMS = tuple(_PARAM_RANGES)                       # the constructor parameters a model file keeps
    _STATE = ("landmark_scale_", "patch_size_", "n_samples_")

    def to_file(self) -> ModelFile:
        """The model as plain arrays and metadata (:mod:`keyshape.base.formats.model`)."""
        self._check_fitted()
        state = {k.rstrip("_"): getattr(self, k) for k in self._STATE}
        arrays = {k.rstrip("_"): getattr(self, k) for k in self._ARRAYS}
        regions = getattr(self, "region_models_", [])
        state["region_models"] = [{"name": r.name, "landmark_scale": r.landmark_scale, "centred": r.centred}
                                  for r in regions]
        if getattr(self, "image_size_", None) is not None:
            state["image_size"] = [int(v) for v in self.image_size_]
        for i, r in enumerate(regions):
            for k in RegionModel.ARRAYS:
                arrays[f"region{i}_{k}"] = getattr(r, k)
        if getattr(self, "lip_refiner_", None) is not None:
            for k in ShapeRefiner.ARRAYS:
                arrays[f"lip_refiner_{k}"] = getattr(self.lip_refiner_, k)
        return ModelFile(self.scheme_, {k: getattr(self, k) for k in self._PARAMS}, state, arrays)

    @classmethod
    def _check_params(cls, params: dict, path=None) -> None:
        """Refuse a model file whose parameters are not of their kind and range (a ``null`` ridge, a
        negative margin): :class:`InputError` naming ``path`` and the parameter."""
        for k, v in params.items():
            if k not in cls._PARAM_RANGES:
                raise InputError(f"model file has an unknown parameter {k!r}", path)
            kind, none, lo, hi = cls._PARAM_RANGES[k]
            if v is None and none:
                continue
            ok = isinstance(v, bool) if kind is bool else (
                not isinstance(v, bool) and isinstance(v, (int, float)) and (kind is float or float(v).is_integer())
                and lo <= v <= hi)
            if not ok:
                want = "true or false" if kind is bool else f"a number in [{lo:g}, {hi:g}]" + (" or null" if none else "")
                raise InputError(f"model file: parameter {k} is {v!r}, not {want}", path)

    @classmethod
    def from_file(cls, mf: ModelFile) -> "AppearanceModel":
        """Rebuild a fitted model from :meth:`to_file`'s content; an inconsistent file is an
        :class:`InputError` naming ``mf.path``."""
        path = mf.path
        try:
            params = dict(mf.params)
            for k, old in (("regions", False), ("split_mouth", False), ("region_grow", 0.06), ("lip_grow", None),
                           ("brow_grow", None), ("centre_eyes", False), ("eye_variance", None),
                           ("lip_refine", False)):
                params.setdefault(k, old)         # files written before region models existed
            cls._check_params(params, path)
            model = cls(mf.scheme, **params)
            for k in cls._ARRAYS:
                a = np.asarray(mf.arrays[k.rstrip("_")])
                if a.dtype.kind not in "biuf" or a.size == 0 or (a.dtype.kind == "f" and not np.isfinite(a).all()):
                    raise InputError(f"model file: array {k.rstrip('_')!r} is empty or holds NaN, infinity or "
                                     "non-numbers", path)
                setattr(model, k, a)
            model.landmark_scale_ = float(mf.state["landmark_scale"])
            model.patch_size_ = int(mf.state["patch_size"])
            model.n_samples_ = int(mf.state["n_samples"])
            size = mf.state.get("image_size")             # absent in models trained before it was recorded
            if size is not None and not (isinstance(size, list) and len(size) == 2 and all(
                    isinstance(v, (int, float)) and float(v).is_integer() and 1 <= v <= 100_000 for v in size)):
                raise InputError(f"model file: image_size {size!r} is not [width, height] in pixels", path)
            model.image_size_ = None if size is None else (int(size[0]), int(size[1]))
            model.region_models_ = [
                RegionModel(str(r["name"]), *(np.asarray(mf.arrays[f"region{i}_{k}"]) for k in RegionModel.ARRAYS),
                            float(r["landmark_scale"]), bool(r.get("centred", False)))
                for i, r in enumerate(mf.state.get("region_models", []))]
            model.lip_refiner_ = ShapeRefiner(*(np.asarray(mf.arrays[f"lip_refiner_{k}"]) for k in ShapeRefiner.ARRAYS)) \
                if model.lip_refine else None
        except KeyError as exc:
            raise InputError(f"model file is missing {exc}", path) from None
        except (TypeError, ValueError, OverflowError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"model file has bad parameters ({exc})", path) from None
        if not (np.isfinite(model.landmark_scale_) and model.landmark_scale_ > 0 and 3 <= model.patch_size_ <= 4096
                and model.n_samples_ >= 1):
            raise InputError("model file is inconsistent (landmark scale, patch size or sample count)", path)
        bad = (model.mask_.ndim != 2 or model.reference_.ndim != 2 or model.reference_.shape[-1:] != (2,)
               or model.components_.ndim != 2 or model.mean_.ndim != 1)
        if bad:
            raise InputError("model file is inconsistent (array dimensions)", path)
        model.mask_ = model.mask_.astype(bool)
        model.scheme_ = mf.scheme
        model.k_ = len(model.components_)
        model._index = np.flatnonzero(model.mask_.ravel())
        n_pix, n_pts = len(model._index), len(model.reference_)
        if (model.mask_.shape != (model.patch_size_,) * 2 or model.components_.shape[1] != n_pix + 2 * n_pts
                or model.mean_.shape != (n_pix + 2 * n_pts,) or n_pts != mf.scheme.n_points or model.k_ < 1
                or not np.isfinite(model.components_).all()):
            raise InputError("model file is inconsistent (array shapes do not match each other or the scheme)", path)
        for r in model.region_models_:
            if any(np.asarray(getattr(r, k)).dtype.kind not in "biuf" for k in RegionModel.ARRAYS) or \
                    r.train_residuals.ndim != 1 or len(r.train_residuals) < 1:
                raise InputError(f"model file is inconsistent (region model {r.name!r})", path)
            x0, y0, w, h = (r.box.tolist() + [0, 0, 0, 0])[:4] if r.box.ndim == 1 else (0, 0, 0, 0)
            if (r.box.shape != (4,) or min(x0, y0) < 0 or w < 1 or h < 1 or x0 + w > model.patch_size_
                    or y0 + h > model.patch_size_ or r.points.ndim != 1 or len(r.points) < 1
                    or r.points.min() < 0 or r.points.max() >= n_pts or r.index.ndim != 1 or len(r.index) < 1
                    or r.index.min() < 0 or r.index.max() >= w * h or r.components.ndim != 2
                    or r.components.shape[1] != len(r.index) + 2 * len(r.points) or len(r.components) < 1
                    or r.mean.shape != (r.components.shape[1],) or r.variance.shape != (len(r.components),)
                    or not (np.isfinite(r.components).all() and np.isfinite(r.mean).all()
                            and np.isfinite(r.variance).all() and np.isfinite(r.train_residuals).all())
                    or not (np.isfinite(r.landmark_scale) and r.landmark_scale > 0)):
                raise InputError(f"model file is inconsistent (region model {r.name!r})", path)
        lr = model.lip_refiner_
        if lr is not None:
            n_pix, k = len(lr.tri), lr.basis.shape[1] if lr.basis.ndim == 2 else 0
            m, nv = len(lr.points), len(lr.ext)
            if (lr.points.ndim != 1 or m < 3 or lr.points.min() < 0 or lr.points.max() >= n_pts
                    or not np.isin(lr.write, lr.points).all() or lr.ext.shape != (nv, m) or nv < 3 or n_pix < 1
                    or lr.tri.shape != (n_pix, 3) or lr.tri.min() < 0 or lr.tri.max() >= nv
                    or lr.bary.shape != (n_pix, 3)
                    or lr.s0.shape != (2 * m,) or lr.basis.shape != (2 * m, k) or k < 1
                    or lr.weights.shape != (k,) or lr.a0.shape != (n_pix,) or lr.qt.ndim != 2
                    or lr.qt.shape[1] != n_pix
                    or not all(np.isfinite(getattr(lr, a)).all() for a in ShapeRefiner.ARRAYS)):
                raise InputError("model file is inconsistent (the lips' shape refiner)", path)
        try:
            with np.errstate(over="raise", invalid="raise", divide="raise"):
                model._precompute()
        except (ValueError, IndexError, FloatingPointError, np.linalg.LinAlgError) as exc:
            raise InputError(f"model file is inconsistent ({type(exc).__name__}: {exc})", path) from None
        return model

    def save(self, path: str | Path) -> None:
        """Write the model as ``.npz`` (format name, version and scheme included), atomically."""
        write_model(path, self.to_file())

    @classmethod
    def load(cls, path: str | Path, scheme: str | Scheme | None = None) -> "AppearanceModel":
        """Read a model written by :meth:`save`; ``scheme`` (optional) must match the model's."""
        return cls.from_file(read_model(path, scheme))
