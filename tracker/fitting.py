"""The tracking loop: pose refinement, eigen-points projection, lost-track detection and recovery.

Section 3 of 004_119ba07521a9af0b.txt; each step in docs/tracker.md, "How each frame is tracked".
Lost frames are returned with ``success = False`` and NaN landmarks.
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Iterable, Iterator

import cv2
import numpy as np

from keyshape.tracker.eigenpoints import AppearanceModel, Pyramid, normalise, pyramid_level, warp_patch, warp_patch_u8
from keyshape.tracker.kernels import lip_box, polish_step, read_global, refine_regions, refine_write
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
        sd_po = sd - q @ (q.T @ sd)
        # weighted Gauss-Newton: pixels that vary a lot between labelled frames (mouth, eyelids)
        # count less, so an expression never seen in training does not drag the pose
        wgt = 1.0 / (noise + var_img.ravel()[self.index])
        hess = sd_po.T @ (sd_po * wgt[:, None])
        self.template = t
        self.update = np.linalg.solve(hess, (sd_po * wgt[:, None]).T)   # (6, n_pix)


class _RegionTables:
    """The region models' constant arrays for :func:`keyshape.tracker.kernels.refine_regions`, padded to
    common sizes (region ``r`` in row ``r``, its pixels, basis rows, coefficients and points first), its
    groups and the work arrays it writes, all allocated once per tracker.

    ``groups`` lists the regions refined together in the order given (``Tracker.read_regions``): each
    region alone, and the lips as one group whose boxes share a stretch and a tilt (``lip_stretch > 0``).
    ``reach`` is the model-frame rectangle ``(x0, y0, x1, y1)`` every sample of the boxes lies in
    (the boxes, a pixel beyond for the interpolation, grown by the largest translation and stretch).
    """

    def __init__(self, groups: list[tuple[list, int, bool]], lim: float, slim: float, n_points: int):
        regions = [rm for members, _, _ in groups for rm in members]
        n_reg = len(regions)
        nmax = max(rm.n_pix for rm in regions)
        kq = max(len(rm.qt) for rm in regions)
        kc = max(len(rm.pinv_i) for rm in regions)
        pmax = max(len(rm.points) for rm in regions)
        geo = np.zeros((n_reg, 6), np.int64)             # box x0, y0, w, h, its pixel count and basis rows
        box_cx, index = np.zeros(n_reg), np.zeros((n_reg, nmax), np.int64)
        mean_i, xc = np.zeros((n_reg, nmax)), np.zeros((n_reg, nmax))
        qt, coef = np.zeros((n_reg, kq, nmax)), np.zeros((n_reg, kc, kq))     # coef: pinv_i Q (coefficients from Qᵀe)
        inv_var, mean_l, ul = np.zeros((n_reg, kc)), np.zeros((n_reg, 2 * pmax)), np.zeros((n_reg, 2 * pmax, kc))
        for r, rm in enumerate(regions):
            x0, y0, w, h = (int(v) for v in rm.box)
            n, q, c, p = rm.n_pix, len(rm.qt), len(rm.pinv_i), len(rm.points)
            geo[r] = x0, y0, w, h, n, q
            box_cx[r] = rm.box_cx
            index[r, :n] = rm.index
            mean_i[r, :n] = rm.mean_i
            xc[r, :n] = rm.box_xc
            qt[r, :q, :n] = rm.qt
            coef[r, :c, :q] = rm.pinv_i @ rm.qt.T
            inv_var[r, :c] = 1.0 / rm.variance
            mean_l[r, :2 * p] = rm.mean_l
            ul[r, :2 * p, :rm.ul.shape[1]] = rm.ul
        table = np.zeros((len(groups), 4), np.int64)     # first, last (exclusive), steps, stretch
        first, widest = 0, 1
        for g, (members, steps, stretch) in enumerate(groups):
            table[g] = first, first + len(members), steps, int(stretch)
            first += len(members)
            widest = max(widest, len(members))
        grow = lim + slim * float(geo[:, 2].max()) / 2 + 2.0
        lo = geo[:, :2].min(0) - 1 - grow
        hi = (geo[:, :2] + geo[:, 2:4]).max(0) + grow
        self.reach = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        hw, npar = int(geo[:, 3].max()) * int(geo[:, 2].max()), 2 * widest + 2
        self.pts = np.zeros((n_reg, pmax, 2))
        # the sum over regions of each point's readings: scatter (n_points, n_reg pmax) @ pts
        self.scatter = np.zeros((n_points, n_reg * pmax))
        for r, rm in enumerate(regions):
            self.scatter[rm.points, r * pmax + np.arange(len(rm.points))] = 1.0
        # what refine_regions takes (its docstring names them): the constant tables and the work arrays
        self.tables = (table, geo, box_cx, index, mean_i, xc, qt, coef, inv_var, mean_l, ul, np.array([lim, slim]))
        self.work = (np.zeros(hw, np.uint8), np.zeros((2, hw)), np.zeros(nmax), np.zeros((4, nmax)), np.zeros((kq, 4)),
                     np.zeros((n_reg, kq)), np.zeros((n_reg, kq)), np.zeros((npar, npar)), np.zeros(npar),
                     np.zeros(npar), np.zeros((n_reg, 4)), self.pts)


def _pose_change(a: np.ndarray, b: np.ndarray) -> tuple:
    """The image-side motion ``m`` from pose ``a`` to pose ``b`` ((2, 3) affines), ``b = m ∘ a``, as 6 floats."""
    (a00, a01, a02), (a10, a11, a12) = a.tolist()
    (b00, b01, b02), (b10, b11, b12) = b.tolist()
    det = a00 * a11 - a01 * a10
    i00, i01, i10, i11 = a11 / det, -a01 / det, -a10 / det, a00 / det           # a's linear part inverted
    m00, m01 = b00 * i00 + b01 * i10, b00 * i01 + b01 * i11
    m10, m11 = b10 * i00 + b11 * i10, b10 * i01 + b11 * i11
    return m00, m01, b02 - m00 * a02 - m01 * a12, m10, m11, b12 - m10 * a02 - m11 * a12


def _moved_on(a: np.ndarray, m: tuple, k: float) -> np.ndarray:
    """``(1 - k) a + k m ∘ a``: pose ``a`` moved on by the fraction ``k`` of the motion ``m`` (:func:`_pose_change`)."""
    (a00, a01, a02), (a10, a11, a12) = a.tolist()
    m00, m01, m02, m10, m11, m12 = m
    j = 1.0 - k
    return np.array([[j * a00 + k * (m00 * a00 + m01 * a10), j * a01 + k * (m00 * a01 + m01 * a11),
                      j * a02 + k * (m00 * a02 + m01 * a12 + m02)],
                     [j * a10 + k * (m10 * a00 + m11 * a10), j * a11 + k * (m10 * a01 + m11 * a11),
                      j * a12 + k * (m10 * a02 + m11 * a12 + m12)]])


class Tracker:
    """Track an :class:`AppearanceModel` through frames (``docs/tracker.md``, "How each frame is tracked").

    Parameters
    ----------
    model : AppearanceModel (fitted)
    n_iter : int
        Alignment iterations per level.
    lost_factor : float
        A frame is lost when its residual exceeds ``lost_factor`` times the largest leave-one-out
        training residual (clipped to [0.15, 0.4]), or when the patch's standard deviation is under
        ``min_contrast`` grey levels (a black or blank frame).
    search : bool
        Recover lost tracks (local search, then global re-initialisation).
    n_polish : int
        Forward-compositional iterations on the eigen residual after the
        coarse-to-fine alignment (:meth:`polish`; 0 to skip).
    reinit_every : int
        While lost, the (costlier) whole-frame search runs every this many frames.
    max_shape_m2 : float
        Plausibility of the shape read: the largest over the global and the region models of the mean
        squared coefficient over its PCA variance, ``mean_j c_j² / λ_j``. Above this the frame is lost;
        from 8 up the confidence falls linearly to 0 here.
    region_iter : int or None
        Translation refinements of each region model per frame (0: read the regions where the global
        pose puts them; -1: ignore the region models). None: 2, and 4 for the region models trained on
        centred crops (``AppearanceModel(centre_eyes=True)``; the counts that differ are in ``region_steps``).
    global_weight : float
        Weight of the global model's reading in the points the region models read:
        ``(1 - w) region + w global``.
    lip_stretch : float
        The lip regions' boxes share a horizontal stretch and a tilt, each at most this fraction
        (0: the lips translate only, as the eyes and brows).
    """

    def __init__(self, model: AppearanceModel, n_iter: int = 5, lost_factor: float = 3.0, search: bool = True,
                 reinit_every: int = 3, n_polish: int = 3, region_iter: int | None = None, min_contrast: float = 3.0,
                 max_shape_m2: float = 30.0, global_weight: float = 0.3, lip_stretch: float = 0.15):
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
        self._m2 = 0.0
        # (pyramid, pose as lists, patch): the full-resolution patch polish() sampled last at the pose it returned,
        # which read() takes instead of sampling it again (the same warp: the same uint8 values)
        self._polished: tuple | None = None
        m = model
        lr = getattr(m, "lip_refiner_", None)
        # the lips' shape fitted by analysis by synthesis after the reading (ShapeRefiner): its constant arrays,
        # work arrays, and where its written points sit among its points and in the frame's points
        self._lips = None if lr is None else (lr, lr.tables(), lr.work(), (np.searchsorted(lr.points, lr.write),
                                              lr.write), np.empty(2 * len(lr.points)), np.empty(4, np.intp))
        size, n_pix, half = m.patch_size_, len(m.index_), m.patch_size_ // 2

        def image(values: np.ndarray) -> np.ndarray:            # values at the mask's pixels -> (..., size, size)
            out = np.zeros(values.shape[:-1] + (size * size,))
            out[..., m.index_] = values
            return out.reshape(values.shape[:-1] + (size, size))

        def down(img: np.ndarray) -> np.ndarray:                # the coarse level's image
            return cv2.resize(img, (half, half), interpolation=cv2.INTER_AREA)

        mean, basis = image(m.mean_[:n_pix]), image(m.components_[:, :n_pix])
        var = image((m.components_[:, :n_pix] ** 2 * m.explained_variance_[:, None]).sum(0))
        noise = float(np.median(m.train_residuals_))
        fine = _Level(mean, basis, m.mask_, np.array([[1.0, 0, 0], [0, 1.0, 0]]), var, noise)
        scale = size / half
        coarse = _Level(down(mean), np.stack([down(b) for b in basis]), down(m.mask_.astype(np.float32)) > 0.99,
                        np.array([[scale, 0, (scale - 1) / 2], [0, scale, (scale - 1) / 2]]), down(var), noise)
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
        self._reading = (m.index_.astype(np.int64), rd.mean_i, np.vstack([rd.pinv_i, rd.basis_i.T]),
                         np.ascontiguousarray(rd.basis_i.T @ rd.basis_i), np.ascontiguousarray(rd.basis_l),
                         rd.mean_l, 1.0 / m.explained_variance_)
        self._read_work = (np.zeros(len(m.index_)), np.zeros(m.k_), np.zeros(2 * m.n_points))
        regions = list(m.region_models_)
        lips = [rm for rm in regions if self._is_lip(rm)]
        count = np.zeros(m.n_points)
        for rm in regions:
            count[rm.points] += 1
        self._region_hit = count > 0               # the points the regions read (the lip corners by two)
        # the compiled regions' tables: each region alone, the lips together
        groups = [([rm], self.region_steps.get(rm.name, self.region_iter), False) for rm in regions
                  if rm not in lips]
        if lips:
            groups.append((lips, max(self.region_steps.get(rm.name, self.region_iter) for rm in lips), True))
        self._tables = _RegionTables(groups, 0.08 * m.face_width, self.lip_stretch, m.n_points) if groups else None
        self._region_count = count
        pe = self.levels[-1]
        self._polish_work = (np.zeros((2, pe.size * pe.size)), np.zeros(len(pe.index)), np.zeros((6, len(pe.index))),
                             np.zeros(pe.q.shape[1]), np.zeros((pe.q.shape[1], 6)), np.zeros((6, 6)), np.zeros(6),
                             np.zeros(6))
        self.reset()

    #: the fraction of the last frame's motion the next frame's alignment starts from (:meth:`step`)
    MOTION_CARRY = 0.5
    #: a frame is lost where more than this fraction of the face's points fall outside the picture (:meth:`_sane`)
    MAX_OUTSIDE = 0.4

    def reset(self) -> None:
        """Forget the previous frame (next frame starts with a whole-frame search)."""
        self.pose = None
        self.last_good = None
        self.lost_for = 0
        self._last_r = 0.0
        self._motion = None             # the last frame's motion (_pose_change): pose_t = motion ∘ pose_t-1

    def state(self) -> dict:
        """What the next :meth:`step` starts from (the previous frame's pose, the last good pose, how long
        the track has been lost, the last residual): :meth:`restore` on another tracker of the same model
        makes it continue exactly as this one would."""
        return {"pose": None if self.pose is None else np.array(self.pose),
                "last_good": None if self.last_good is None else np.array(self.last_good),
                "lost_for": int(self.lost_for), "last_r": float(self._last_r),
                "motion": self._motion}

    def restore(self, state: dict) -> None:
        """Continue from a :meth:`state` (of this tracker or another of the same model)."""
        self.pose = None if state["pose"] is None else np.array(state["pose"], np.float64)
        self.last_good = None if state["last_good"] is None else np.array(state["last_good"], np.float64)
        self.lost_for = int(state["lost_for"])
        self._last_r = float(state["last_r"])
        self._motion = None if state.get("motion") is None else tuple(float(v) for v in state["motion"])

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
        sol = self._polish_work[-1]
        level = (lv.index, lv.qt, lv.template, lv.xx, lv.yy)
        best_r, its = None, 0
        prev = prev_patch = None                            # the last pose kept and its patch
        self._polished = None
        for _ in range(self.n_polish):
            patch = warp_patch_u8(pyr, a, lv.size)
            r, ok = polish_step(patch, level, self._polish_work)
            if best_r is not None and r >= best_r:
                a = prev
                self._polished = (pyr, a.tolist(), prev_patch)   # read() at this pose samples the same patch
                break
            best_r, prev, prev_patch = r, a, patch
            if not ok:
                break
            d0, d1, d2, d3, d4, d5 = sol.tolist()
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
        flat = self._read_work[2]
        r, self._contrast, self._m2 = read_global(patch, self._reading, self._read_work)
        shape = flat.reshape(-1, 2).copy()
        if m.region_models_ and self.region_iter >= 0:
            hit, reg = self.read_regions(pyr, pose, patch)
            w = self.global_weight
            shape[hit] = reg if not w else (1.0 - w) * reg + w * shape[hit]
        return shape, apply_affine(pose, shape), r

    #: Gauss-Newton steps of the lips' shape fit a frame (each stops early once no parameter moves by 1e-3)
    LIP_STEPS = 6

    def refine_lips(self, pyr: Pyramid, pose: np.ndarray, points: np.ndarray) -> None:
        """Fit the lips' shape to the frame from the reading ``points`` (image pixels, updated in place: the
        refiner's written points) by :func:`~keyshape.tracker.kernels.refine_shape` (the model's
        :class:`~keyshape.tracker.eigenpoints.ShapeRefiner`); :meth:`step` calls it once a frame, on the pose
        and reading it keeps."""
        lr, tables, work, where, s, box = self._lips
        lvl, f = lr.level(pyr, pose)
        if lip_box(pose, points, lr.points, f, pyr._sizes[lvl], s, box):
            refine_write(lr.crop(pyr, lvl, box), f, pose, box, s, tables, work, self.LIP_STEPS, where, points)

    def read_regions(self, pyr: Pyramid, pose: np.ndarray, patch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every region model's points: each region's box translated in the model frame (at most
        ``region_iter`` Gauss-Newton steps on its distance from its own appearance subspace, forward additive,
        each kept only if it lowers that distance, ``|t|`` at most 8% of the face width), the lips' boxes
        together with one shared horizontal stretch and tilt as well (``lip_stretch``), then each region's
        eigen-points at the best motion; one call of the compiled
        :func:`~keyshape.tracker.kernels.refine_regions` (``docs/tracker.md``).

        Returns
        -------
        hit : (n_points,) bool, the points the regions read
        shape : (n_hit, 2) their model-frame positions (the mean where two regions read a point)
        """
        acc = np.zeros((self.model.n_points, 2))
        if self._tables is not None:
            acc += self._tables.scatter @ self._run_tables(self._tables, pyr, pose, patch).reshape(-1, 2)
        hit = self._region_hit
        return hit, acc[hit] / self._region_count[hit, None]

    def _run_tables(self, tb: _RegionTables, pyr: Pyramid, pose: np.ndarray, patch: np.ndarray) -> np.ndarray:
        """Refine and read the groups of ``tb`` at ``pose`` (:func:`~keyshape.tracker.kernels.refine_regions`):
        ``tb.pts``, each region's model-frame points (``self._m2`` raised to their largest ``mean c²/λ``)."""
        lvl = pyramid_level(pyr, pose)
        f = 0.5 ** lvl
        (a00, a01, a02), (a10, a11, a12) = pose.tolist()
        # the level's window every box sample lies in (the rectangle tb.reach of the model frame)
        x0, y0, x1, y1 = tb.reach
        xs = [a00 * x + a01 * y + a02 for x in (x0, x1) for y in (y0, y1)]
        ys = [a10 * x + a11 * y + a12 for x in (x0, x1) for y in (y0, y1)]
        d = 0.5 * f - 0.5
        lx0, lx1, ly0, ly1 = min(xs) * f + d, max(xs) * f + d, min(ys) * f + d, max(ys) * f + d
        if all(map(math.isfinite, (lx0, lx1, ly0, ly1))) and max(-lx0, -ly0, lx1, ly1) < 1e7:
            img = pyr.window(lvl, math.floor(lx0) - 2, math.floor(ly0) - 2, math.ceil(lx1) + 3, math.ceil(ly1) + 3)
        else:
            img = pyr[lvl]
        m2 = refine_regions(img, f, pose.ravel(), patch, tb.tables, tb.work)
        self._m2 = max(self._m2, m2)
        return tb.pts

    def _is_lip(self, rm) -> bool:
        return self.lip_stretch > 0 and rm.name.startswith(("lip", "mouth"))

    def _sane(self, pose: np.ndarray, shape: np.ndarray, pts: np.ndarray, image_size: tuple[int, int]) -> bool:
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
        # most of the face outside the picture: its points there are the model's guess (docs/tracker.md, "Close-ups")
        outside = (pts[:, 0] < -0.5) | (pts[:, 0] > w - 0.5) | (pts[:, 1] < -0.5) | (pts[:, 1] > h - 0.5)
        if outside.mean() > self.MAX_OUTSIDE:
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
              and self._sane(pose, shape, pts, image_size))
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
        """Track one frame (BGR or gray uint8).

        The alignment starts from the previous frame's pose moved on by ``MOTION_CARRY`` of that frame's
        own motion (a damped constant-velocity prediction, where the two frames before were both tracked):
        a face moving fast stays within the polish's reach (docs/tracker.md, "Fast motion").
        """
        pyr = Pyramid(frame)            # gray conversion and downsampling only where the face is looked at
        size = pyr.size
        n_pts = self.model.n_points
        best = None
        its_total = 0
        prev = self.pose
        if prev is not None:
            start = prev if self._motion is None else _moved_on(prev, self._motion, self.MOTION_CARRY)
            # fast path: small motion needs only the full-resolution polish; fall back to the
            # coarse-to-fine alignment when the residual is not as good as the previous frame's
            ok, r, pose, pts, its, m2 = self._evaluate(pyr, start, size, levels=())
            its_total += its
            if not (ok and r <= 1.2 * self._last_r + 0.01):
                ok2, r2, pose2, pts2, its, m22 = self._evaluate(pyr, start, size)
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
        if ok and self._lips is not None:
            self.refine_lips(pyr, pose, pts)
        conf = min(max((self.lost_threshold - r) / max(self.lost_threshold - self.ref_residual, 1e-9), 0.0), 1.0,
                   max((self.max_shape_m2 - m2) / (self.max_shape_m2 - self.typical_shape_m2), 0.0))
        if ok:
            # the motion from the previous frame's pose, where that frame was tracked (not a held pose)
            self._motion = None if prev is None or self.lost_for else _pose_change(prev, pose)
            self.pose = pose
            self.last_good = pose
            self._last_r = r
            self.lost_for = 0
        else:
            self._motion = None
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
