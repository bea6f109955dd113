"""Render one frame of the synthetic face: model-frame canvas, head pose warp, camcorder degradations.

Design notes and figures: docs/synth.md, "Notes on the code", ``data_synth/render.py``.
"""
from __future__ import annotations

import cv2
import numpy as np

from keyshape.data_synth.face_model import COMPONENTS, FaceModel
from keyshape.data_synth.performance import Performance

_SHIFT = 4
_ONE = 1 << _SHIFT
_SUPER = 4      # supersampling of filled polygons
_C = {name: k for k, name in enumerate(COMPONENTS)}

_SKIN = np.array([[0.58, 0.64, 0.88], [0.46, 0.55, 0.80], [0.32, 0.42, 0.62], [0.64, 0.70, 0.92],
                  [0.52, 0.60, 0.86]])
_HAIR = np.array([[0.07, 0.08, 0.10], [0.10, 0.16, 0.24], [0.20, 0.32, 0.45], [0.05, 0.05, 0.06]])
_IRIS = np.array([[0.10, 0.22, 0.36], [0.55, 0.42, 0.25], [0.30, 0.42, 0.28], [0.14, 0.26, 0.40]])
_LIP = np.array([[0.36, 0.32, 0.70], [0.40, 0.34, 0.74], [0.33, 0.28, 0.62]])
_SHIRT = np.array([[0.45, 0.25, 0.12], [0.20, 0.20, 0.22], [0.55, 0.55, 0.50], [0.15, 0.30, 0.50]])


def _noise(shape, sigma, rng) -> np.ndarray:
    """Smooth noise of unit standard deviation: white noise blurred with ``sigma`` pixels."""
    x = rng.standard_normal(shape).astype(np.float32)
    if sigma > 0.3:
        x = cv2.GaussianBlur(x, (0, 0), sigma)
    return x / max(float(x.std()), 1e-6)


def _poly_mask(shape, polys, origin=(0.0, 0.0), closed=True, thickness: int | None = None) -> np.ndarray:
    """Coverage in [0, 1] of polygons (or polylines ``thickness`` px wide) on a pixel grid of ``shape``.

    Filled polygons are rasterised at ``_SUPER`` times the resolution and
    area-averaged, so the 50 % coverage contour follows the polygon to about
    1/8 pixel (OpenCV's own anti-aliased fill grows shapes by about half a
    pixel). Polylines (non-ground-truth strokes) use OpenCV's anti-aliasing.
    """
    if thickness is None:
        S = _SUPER
        m = np.zeros((shape[0] * S, shape[1] * S), np.uint8)
        pts = [np.round(((np.asarray(p) - origin) * S + (S - 1) / 2) * _ONE).astype(np.int32).reshape(-1, 1, 2)
               for p in polys]
        cv2.fillPoly(m, pts, 255, cv2.LINE_8, _SHIFT)
        m = cv2.resize(m, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    else:
        m = np.zeros(shape, np.uint8)
        pts = [np.round((np.asarray(p) - origin) * _ONE).astype(np.int32).reshape(-1, 1, 2) for p in polys]
        cv2.polylines(m, pts, closed, 255, max(1, int(thickness)), cv2.LINE_AA, _SHIFT)
    return m.astype(np.float32) * (1.0 / 255.0)


def _closed(upper: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """Closed polygon from an upper and a lower curve that share their end points."""
    return np.concatenate([upper, lower[::-1][1:-1]], axis=0)


def _affine_inv(m: np.ndarray) -> np.ndarray:
    return cv2.invertAffineTransform(np.asarray(m, dtype=np.float64))


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Affine ``a @ b`` for 2x3 matrices (apply ``b`` first)."""
    A = np.vstack([a, [0, 0, 1]])
    B = np.vstack([b, [0, 0, 1]])
    return (A @ B)[:2]


class FaceRenderer:
    """Draws frames of one synthetic face for one image size.

    Parameters
    ----------
    model : FaceModel
    size : (width, height) of the frames in pixels.
    rng : None, int or numpy.random.Generator
        Draws the look (skin, hair, iris, lip and shirt colours, skin texture,
        background room); fixed for a seed.

    Attributes
    ----------
    model_scale : float
        Image pixels per model unit at head scale 1 (``min(W / 640, H / 480)``).
    canvas_from_model : (2, 3) affine from the model frame to canvas pixels.
    """

    # model-frame extent of the canvas
    XMIN, XMAX, YMIN, YMAX = -150.0, 150.0, -190.0, 265.0
    PIVOT = np.array([0.0, 170.0])    # head rotates and scales about the neck

    def __init__(self, model: FaceModel, size=(640, 480), rng=None):
        rng = np.random.default_rng(rng)
        r_look, r_tex, r_bg = rng.spawn(3)
        self.model = model
        self.size = (int(size[0]), int(size[1]))
        W, H = self.size
        self.model_scale = min(W / 640.0, H / 480.0)
        self.ppu = self.model_scale * 1.1
        ppu = self.ppu
        self.canvas_from_model = np.array([[ppu, 0, -self.XMIN * ppu], [0, ppu, -self.YMIN * ppu]])
        self._off = self.canvas_from_model[:, 2]
        cw = int(np.ceil((self.XMAX - self.XMIN) * ppu))
        ch = int(np.ceil((self.YMAX - self.YMIN) * ppu))
        self.canvas_shape = (ch, cw)
        self.anchor = np.array([W * 0.5, H * 0.43])
        # look
        self.skin = _SKIN[r_look.integers(len(_SKIN))] * r_look.uniform(0.95, 1.05, 3)
        self.hair = _HAIR[r_look.integers(len(_HAIR))] * r_look.uniform(0.9, 1.1, 3)
        self.iris = _IRIS[r_look.integers(len(_IRIS))] * r_look.uniform(0.9, 1.1, 3)
        self.lip = _LIP[r_look.integers(len(_LIP))] * (self.skin / _SKIN[0]) ** 0.5
        self.shirt = _SHIRT[r_look.integers(len(_SHIRT))] * r_look.uniform(0.85, 1.15, 3)
        self.iris_phase = r_look.uniform(0, 2 * np.pi, 4)
        self._build_face(r_tex)
        self._build_scene(r_bg)
        self._neutral = model.curves(np.zeros((1, len(COMPONENTS))))

    # ------------------------------------------------------------------ static layers
    def _grid(self):
        ch, cw = self.canvas_shape
        xs = (np.arange(cw, dtype=np.float32) - self._off[0]) / self.ppu
        ys = (np.arange(ch, dtype=np.float32) - self._off[1]) / self.ppu
        return np.meshgrid(xs, ys)

    def _build_face(self, rng: np.random.Generator) -> None:
        X, Y = self._grid()
        ppu = self.ppu
        g = lambda x0, y0, sx, sy: np.exp(-((X - x0) / sx) ** 2 - ((Y - y0) / sy) ** 2)  # noqa: E731
        # head: egg-shaped (narrower jaw), ears, neck
        a = 112.0 * (1 - 0.22 * np.clip((Y - 10) / 140, 0, 1) ** 1.6)
        f_head = (X / a) ** 2 + ((Y + 5) / 150.0) ** 2
        head = f_head < 1
        f_neck = np.abs(X) / (60.0 + 0.3 * np.clip(Y - 150, 0, None))
        neck = (f_neck < 1) & (Y > 40)
        ears = [((X - s * 110) / 13.0) ** 2 + ((Y + 2) / 27.0) ** 2 < 1 for s in (-1, 1)]
        # height field for the normals
        hgt = 95.0 * np.sqrt(np.clip(1 - f_head, 0, 1))
        hgt = hgt + 11 * g(0, 5, 8.5, 32) * (Y < 40) + 10 * g(0, 36, 8, 8) + 5 * g(-12, 41, 6, 5) + 5 * g(12, 41, 6, 5)
        ex, ey = self.model.eye_centres[1]          # eye sockets and eyeballs where this face's eyes are
        hgt = hgt + 5 * g(0, ey - 24, 70, 8) - 7 * g(-ex, ey, 22, 13) - 7 * g(ex, ey, 22, 13)
        hgt = hgt + 4 * g(-ex, ey, 11, 8) + 4 * g(ex, ey, 11, 8) + 6 * g(-60, 12, 22, 18) + 6 * g(60, 12, 22, 18)
        hgt = hgt + 6 * g(0, 80, 28, 11) + 6 * g(0, 132, 18, 14) - 3 * g(0, 106, 16, 5)
        neck_h = 60.0 * np.sqrt(np.clip(1 - f_neck ** 2, 0, 1)) - 25
        hgt = np.where(head, hgt, np.where(neck, neck_h, 0.0))
        # hair volume: a slightly larger ellipsoid over the top of the head
        f_hair = (X / 126.0) ** 2 + ((Y + 18) / 170.0) ** 2
        hair_h = 100.0 * np.sqrt(np.clip(1 - f_hair, 0, 1)) - 10.0
        hgt = hgt + np.clip((-Y - 20) / 40, 0, 1) * np.clip(hair_h - hgt, 0, None)
        for e in ears:
            hgt = np.where(e & ~head, 30.0, hgt)
        hgt = cv2.GaussianBlur(hgt.astype(np.float32), (0, 0), 1.2 * ppu)
        gy, gx = np.gradient(hgt, 1.0 / ppu)
        nz = np.ones_like(gx)
        norm = np.sqrt(gx ** 2 + gy ** 2 + 1)
        self._n = np.ascontiguousarray(np.dstack([-gx / norm, -gy / norm, nz / norm]).astype(np.float32))  # (h, w, 3)
        # albedo: skin with multi-scale texture
        tex = (1 + 0.03 * _noise(X.shape, 9 * ppu, rng) + 0.025 * _noise(X.shape, 2.5 * ppu, rng)
               + 0.03 * _noise(X.shape, 0.6 * ppu, rng))
        red = 0.03 * _noise(X.shape, 14 * ppu, rng)
        albedo = np.empty(X.shape + (3,), np.float32)
        for c in range(3):
            albedo[..., c] = self.skin[c] * tex
        albedo[..., 2] *= 1 + red
        albedo[..., 1] *= 1 - 0.2 * red
        blush = 0.08 * (g(-62, 30, 22, 16) + g(62, 30, 22, 16))
        albedo[..., 2] += blush * 0.5
        albedo[..., 0] -= blush * 0.3
        # nostrils and the shadow under the nose
        for s in (-1, 1):
            nost = ((X - s * 9) / 5.0) ** 2 + ((Y - 45) / 2.6) ** 2 < 1
            albedo[nost] *= 0.35
        albedo *= (1 - 0.25 * g(0, 50, 14, 4))[..., None]
        # ears: a darker inner fold
        for s, e in zip((-1, 1), ears):
            albedo[e & ~head] *= 1.05
            inner = ((X - s * 112) / 6.0) ** 2 + ((Y + 2) / 16.0) ** 2 < 1
            albedo[inner & ~head] *= 0.7
        # neck in the jaw's shadow
        below = np.clip((Y - 120) / 60, 0, 1)
        occl = np.where(neck & ~head, 0.55 + 0.45 * below, 1.0)
        albedo *= occl[..., None]
        # hair: cap above a hairline, sides down to the temples, strand texture
        hairline = -102 + 88 * np.clip((np.abs(X) - 68) / 48, 0, 1) ** 1.5 + 4 * np.cos(X / 9.0)
        strands = rng.standard_normal(X.shape).astype(np.float32)
        strands = cv2.GaussianBlur(strands, (0, 0), sigmaX=0.7 * ppu, sigmaY=7 * ppu)
        strands /= strands.std()
        edge_noise = 3.0 * _noise(X.shape, 3 * ppu, rng)
        hair = (f_hair < 1 + edge_noise * 0.01) & (Y < hairline + edge_noise) & (Y < 20)
        n_lab, lab, stats, _ = cv2.connectedComponentsWithStats(hair.astype(np.uint8), connectivity=8)
        if n_lab > 1:        # keep the one hair region, drop islands of the edge noise
            hair = lab == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        hair_tex = (1 + 0.22 * strands + 0.1 * _noise(X.shape, 12 * ppu, rng)) * (0.8 + 0.2 * np.clip(-Y / 150, 0, 1))
        for c in range(3):
            albedo[..., c] = np.where(hair, self.hair[c] * hair_tex, albedo[..., c])
        # forehead wrinkles (shown with the brow raise)
        wr = np.zeros(X.shape, np.float32)
        for k, y0 in enumerate((-72, -80, -88)):
            yy = y0 + 3 * np.sin(X / 25.0 + k)
            wr += np.exp(-((Y - yy) / 0.9) ** 2) * np.exp(-(X / 55.0) ** 4)
        self._wrinkles = wr
        self._spec_mask = np.where(hair, 0.0, 0.12).astype(np.float32)
        mask = (head | neck | ears[0] | ears[1] | hair).astype(np.float32)
        self._alpha = cv2.GaussianBlur(mask, (0, 0), 0.6 * ppu)
        self._albedo = albedo
        # jaw: below the mouth the face follows the lower lip down (the chin drops with the jaw)
        my = float(self.model.mouth_centre[1])
        cx0, cy0 = self._to_canvas(np.array([-128.0, my - 6.0])).astype(int)
        cx1, cy1 = self._to_canvas(np.array([128.0, 235.0])).astype(int)
        self._jaw_roi = (max(cy0, 0), min(cy1, self.canvas_shape[0]), max(cx0, 0), min(cx1, self.canvas_shape[1]))
        y0, y1, x0, x1 = self._jaw_roi
        jx, jy = X[y0:y1, x0:x1], Y[y0:y1, x0:x1]
        sstep = lambda v: np.clip(v, 0, 1) ** 2 * (3 - 2 * np.clip(v, 0, 1))  # noqa: E731
        prof = sstep((jy - (my - 4)) / 24) * (1 - sstep((jy - 150) / 75)) * (1 - sstep((np.abs(jx) - 50) / 65))
        self._jaw_prof = (prof * ppu).astype(np.float32)
        gx_, gy_ = np.meshgrid(np.arange(x0, x1, dtype=np.float32), np.arange(y0, y1, dtype=np.float32))
        self._jaw_grid = (gx_, gy_)
        self._fine = _noise(X.shape, 0.5 * ppu, rng)
        self._tex = tex.astype(np.float32)
        rows = np.flatnonzero(np.abs(wr).max(axis=1) > 0.01)
        self._wrinkle_rows = slice(int(rows.min()), int(rows.max()) + 1)

    def _build_scene(self, rng: np.random.Generator) -> None:
        W, H = self.size
        s = self.model_scale
        xs, ys = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
        wall = np.array(rng.choice([[0.55, 0.60, 0.62], [0.45, 0.55, 0.62], [0.62, 0.62, 0.55],
                                    [0.40, 0.45, 0.40]])) * rng.uniform(0.9, 1.1, 3)
        grad = 0.85 + 0.25 * (1 - ys / H) + 0.1 * np.sin(xs / W * 2.5 + rng.uniform(0, 6))
        bg = wall[None, None, :] * grad[..., None] * (1 + 0.04 * _noise((H, W), 20 * s, rng))[..., None]
        bg = bg.astype(np.float32)
        # furniture, out of focus: a bookshelf on one side, a framed picture on the other
        side = 1 if rng.random() < 0.5 else -1
        sx0, sx1 = (0.70 * W, 0.99 * W) if side > 0 else (0.01 * W, 0.30 * W)
        sy0, sy1 = 0.04 * H, 0.80 * H
        wood = np.array([0.16, 0.26, 0.38]) * rng.uniform(0.7, 1.3)
        inside_shelf = (xs > sx0) & (xs < sx1) & (ys > sy0) & (ys < sy1)
        bg[inside_shelf] = wood * 0.45
        n_shelves = 3
        gap = (sy1 - sy0) / n_shelves
        for k in range(n_shelves):          # loops over shelves and books, once per seed
            top, bottom = sy0 + k * gap, sy0 + (k + 1) * gap
            bg[(xs > sx0) & (xs < sx1) & (ys > bottom - 0.018 * H) & (ys < bottom)] = wood
            x = sx0 + 0.01 * W
            while x < sx1 - 0.04 * W:
                bw = rng.uniform(0.01, 0.03) * W
                bh = rng.uniform(0.55, 0.92) * (gap - 0.02 * H)
                col = rng.uniform(0.1, 0.75, 3) * rng.uniform(0.5, 1.0)
                book = (xs > x) & (xs < x + bw) & (ys > bottom - 0.018 * H - bh) & (ys < bottom - 0.018 * H)
                bg[book] = col
                x += bw + rng.uniform(0.0, 0.006) * W
        px0, px1 = (0.05 * W, 0.24 * W) if side > 0 else (0.76 * W, 0.95 * W)
        py0, py1 = 0.10 * H, 0.38 * H
        frame_m = (xs > px0) & (xs < px1) & (ys > py0) & (ys < py1)
        bg[frame_m] = np.array([0.12, 0.12, 0.13]) * rng.uniform(0.5, 2.0)
        inner = (xs > px0 + 0.012 * W) & (xs < px1 - 0.012 * W) & (ys > py0 + 0.012 * W) & (ys < py1 - 0.012 * W)
        art = np.stack([_noise((H, W), 10 * s, rng) for _ in range(3)], axis=-1) * 0.07 + rng.uniform(0.3, 0.6, 3)
        bg[inner] = art[inner]
        lamp = np.exp(-(((xs - rng.uniform(0, W)) / (0.2 * W)) ** 2 + ((ys - 0.15 * H) / (0.2 * H)) ** 2))
        bg += 0.25 * lamp[..., None].astype(np.float32)
        self._background = cv2.GaussianBlur(bg, (0, 0), 4.0 * s)
        # torso: shoulders and collar in model coordinates, drawn at scale 1 and shifted with the head
        sh = [(-300, 420), (-280, 262), (-190, 222), (-62, 196), (0, 250), (62, 196), (190, 222),
              (280, 262), (300, 420)]
        pts = np.array(sh, float) * s + self.anchor
        m = _poly_mask((H, W), [pts])
        m = cv2.GaussianBlur(m, (0, 0), 0.8 * s)
        fold = 1 + 0.12 * _noise((H, W), 10 * s, rng)
        shade = np.clip(1.0 - 0.3 * (np.abs(xs - self.anchor[0]) / (280 * s)) ** 2, 0.5, 1)
        col = self.shirt[None, None, :] * (fold * shade)[..., None]
        collar = _poly_mask((H, W), [np.array([(-62, 196), (0, 250), (62, 196), (0, 262)]) * s + self.anchor],
                            thickness=max(1, int(round(4 * s))))
        col = col * (1 - 0.5 * collar[..., None])
        # only rows that the torso can reach (it moves with the head by at most ~60 model units up)
        rows = np.flatnonzero(m.max(axis=1) > 0)
        self._torso_top = int(max(rows.min() - 80 * s, 0)) if len(rows) else H - 1
        top = self._torso_top
        self._torso_pm = np.ascontiguousarray((col * m[..., None]).astype(np.float32)[top:])
        self._torso_a = np.ascontiguousarray(m.astype(np.float32)[top:])
        # torso layer is stored from row ``top`` down: a translation by (dx, dy) still applies as is
        # sensor noise field (std 0.013 per frame after subtracting two independent crops)
        self._noise = (rng.standard_normal((H + 64, W + 64, 3)).astype(np.float32) * np.float32(0.013))
        r = np.hypot((xs - W / 2) / W, (ys - H / 2) / H)
        self._vignette = np.repeat((1 - 0.35 * r ** 2)[..., None], 3, axis=2).astype(np.float32)

    # ------------------------------------------------------------------ pose
    def poses(self, perf: Performance) -> np.ndarray:
        """``image_from_model`` affine maps ``(n_frames, 2, 3)`` of a performance's head motion.

        The head rotates by ``roll_deg`` and scales by ``scale`` about the neck
        pivot, then moves by ``shift`` (model units): at rest the model origin
        sits at ``anchor`` and one model unit is ``model_scale`` pixels.
        """
        th = np.deg2rad(perf.roll_deg)
        k = self.model_scale * perf.scale
        A = np.empty((perf.n_frames, 2, 2))
        A[:, 0, 0] = k * np.cos(th)
        A[:, 0, 1] = -k * np.sin(th)
        A[:, 1, 0] = k * np.sin(th)
        A[:, 1, 1] = k * np.cos(th)
        t = self.anchor + self.model_scale * (self.PIVOT + perf.shift) - A @ self.PIVOT
        return np.concatenate([A, t[:, :, None]], axis=2)

    # ------------------------------------------------------------------ per-frame drawing
    def _to_canvas(self, p: np.ndarray) -> np.ndarray:
        return p * self.ppu + self._off

    def _roi(self, pts: np.ndarray, pad_x: float, pad_top: float, pad_bottom: float):
        ch, cw = self.canvas_shape
        x0 = int(max(np.floor(pts[:, 0].min() - pad_x), 0))
        x1 = int(min(np.ceil(pts[:, 0].max() + pad_x) + 1, cw))
        y0 = int(max(np.floor(pts[:, 1].min() - pad_top), 0))
        y1 = int(min(np.ceil(pts[:, 1].max() + pad_bottom) + 1, ch))
        return x0, x1, y0, y1

    def _draw_brow(self, img: np.ndarray, spine: np.ndarray, inner_right: bool) -> None:
        ppu = self.ppu
        sp = self._to_canvas(spine)
        n = len(sp)
        # v: 0 at the inner end, 1 at the outer end (the spine runs image-left to image-right)
        v = np.linspace(1, 0, n) if inner_right else np.linspace(0, 1, n)
        th = (9.0 - 6.5 * v ** 1.1) * ppu
        d = np.gradient(sp, axis=0)
        nrm = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.linalg.norm(d, axis=1, keepdims=True)
        top = sp - nrm * (th[:, None] / 2)
        bot = sp + nrm * (th[:, None] / 2)
        poly = np.concatenate([top, bot[::-1]])
        x0, x1, y0, y1 = self._roi(poly, 2, 2, 2)
        m = _poly_mask((y1 - y0, x1 - x0), [poly], (x0, y0))
        m = cv2.GaussianBlur(m, (0, 0), 0.5 * ppu)
        m *= 0.8 + 0.1 * np.clip(self._fine[y0:y1, x0:x1], -2, 2)
        roi = img[y0:y1, x0:x1]
        roi *= (1 - m)[..., None]
        roi += m[..., None] * (0.8 * self.hair).astype(np.float32)

    def _draw_eye(self, img: np.ndarray, upper: np.ndarray, lower: np.ndarray, iris: np.ndarray,
                  neutral_upper: np.ndarray, light: np.ndarray) -> None:
        ppu = self.ppu
        up, lo = self._to_canvas(upper), self._to_canvas(lower)
        crease = self._to_canvas(neutral_upper + [0.0, -6.0])
        ic = self._to_canvas(iris)
        x0, x1, y0, y1 = self._roi(np.vstack([up, lo, crease]), 4 * ppu, 4 * ppu, 4 * ppu)
        shape = (y1 - y0, x1 - x0)
        roi = img[y0:y1, x0:x1]
        org = (x0, y0)
        # lid crease and lower-lid line: soft darkening of the skin
        cm = _poly_mask(shape, [crease], org, closed=False, thickness=round(1.5 * ppu))
        cm = cv2.GaussianBlur(cm, (0, 0), 0.8 * ppu)
        roi *= (1 - 0.35 * cm)[..., None]
        lm = _poly_mask(shape, [lo + [0, 0.6 * ppu]], org, closed=False, thickness=round(1.5 * ppu))
        roi *= (1 - 0.25 * lm)[..., None]
        # lash line just above the upper lid edge (the eye interior is drawn over its lower half)
        lash = _poly_mask(shape, [up - [0, 1.2 * ppu]], org, closed=False, thickness=round(3.2 * ppu))
        roi *= (1 - 0.9 * lash)[..., None]
        roi += (0.9 * lash)[..., None] * (0.3 * self.hair)
        # eye interior on the ROI grid
        gx = np.arange(x0, x1, dtype=np.float32)[None, :]
        gy = np.arange(y0, y1, dtype=np.float32)[:, None]
        yu = np.interp(gx[0], up[:, 0], up[:, 1]).astype(np.float32)[None, :]
        below_lid = (gy - yu) / ppu
        xc = (gx - (up[0, 0] + up[-1, 0]) / 2) / (up[-1, 0] - up[0, 0]) * 2
        sclera = np.array([0.80, 0.84, 0.88], np.float32) * (
            (1 - 0.3 * np.exp(-np.clip(below_lid, 0, None) / 0.9)) * (1 - 0.25 * xc ** 4))[..., None]
        dx, dy = gx - ic[0], gy - ic[1]
        r = np.sqrt(dx * dx + dy * dy) / ppu
        R, Rp = self.model.iris_radius, self.model.pupil_radius
        ang = np.arctan2(dy, dx)
        streak = 1 + 0.07 * (np.sin(7 * ang + self.iris_phase[0]) + np.sin(13 * ang + self.iris_phase[1])
                             + np.sin(23 * ang + self.iris_phase[2]) + np.sin(37 * ang + self.iris_phase[3]))
        radial = 0.75 + 0.45 * np.exp(-((r - 1.5 * Rp) / 2.0) ** 2) - 0.45 * np.clip((r - 0.8 * R) / (0.2 * R), 0, 1)
        iris = self.iris[None, None, :].astype(np.float32) * (streak * radial)[..., None]
        iris *= (1 - 0.3 * np.exp(-np.clip(below_lid, 0, None) / 0.9))[..., None]
        ci = np.clip((R - r) * ppu + 0.5, 0, 1)[..., None]
        cp = np.clip((Rp - r) * ppu + 0.5, 0, 1)[..., None]
        col = sclera * (1 - ci) + iris * ci
        col = col * (1 - cp) + np.float32(0.025) * cp
        # corneal highlight towards the light, outside the pupil
        hdir = np.array([light[0], light[1]]) / max(np.hypot(light[0], light[1]), 1e-6)
        hx, hy = ic + hdir * 6.2 * ppu
        hl = np.exp(-((gx - hx) ** 2 + (gy - hy) ** 2) / (2 * (0.8 * ppu) ** 2))
        col += (0.9 * hl)[..., None]
        m = _poly_mask(shape, [_closed(up, lo)], org)[..., None]
        roi *= 1 - m
        roi += m * col

    def _draw_mouth(self, img: np.ndarray, c: dict) -> None:
        ppu = self.ppu
        ou, ol = self._to_canvas(c["lip_outer_upper"]), self._to_canvas(c["lip_outer_lower"])
        iu, il = self._to_canvas(c["lip_inner_upper"]), self._to_canvas(c["lip_inner_lower"])
        x0, x1, y0, y1 = self._roi(np.vstack([ou, ol]), 3 * ppu, 3 * ppu, 3 * ppu)
        shape = (y1 - y0, x1 - x0)
        org = (x0, y0)
        roi = img[y0:y1, x0:x1]
        gx = np.arange(x0, x1, dtype=np.float32)[None, :]
        gy = np.arange(y0, y1, dtype=np.float32)[:, None]
        yiu = np.interp(gx[0], iu[:, 0], iu[:, 1]).astype(np.float32)[None, :]
        yil = np.interp(gx[0], il[:, 0], il[:, 1]).astype(np.float32)[None, :]
        yol = np.interp(gx[0], ol[:, 0], ol[:, 1]).astype(np.float32)[None, :]
        tex = self._tex[y0:y1, x0:x1]
        upper_lip = gy < yiu
        shade = np.where(upper_lip, 0.78, 1.0 + 0.15 * np.exp(-((gy - (yil + 0.45 * (yol - yil))) / (2.5 * ppu)) ** 2))
        lip = self.lip[None, None, :].astype(np.float32) * (tex * shade)[..., None]
        mo = _poly_mask(shape, [_closed(ou, ol)], org)[..., None]
        roi *= 1 - mo
        roi += mo * lip
        # mouth interior: dark, upper teeth under the upper lip, tongue and lower teeth above the lower lip
        opening = (yil - yiu) / ppu
        from_top = (gy - yiu) / ppu
        from_bottom = (yil - gy) / ppu
        inside = np.array([0.06, 0.05, 0.12], np.float32)
        col = np.broadcast_to(inside, shape + (3,)).copy()
        col *= (0.6 + 0.4 * np.clip(from_bottom / 6, 0, 1) * np.clip(from_top / 6, 0, 1))[..., None]
        tongue = (from_bottom < 7) & (opening > 9)
        col[tongue] = [0.22, 0.22, 0.45]
        mx = self._to_canvas(self.model.mouth_centre)[0]
        gaps = 0.8 + 0.2 * np.abs(np.cos(np.pi * (gx - mx) / (7.5 * ppu))) ** 0.3
        teeth_u = (from_top < 4.5) & (opening > 1.5)
        teeth_l = (from_bottom < 2.5) & (opening > 12)
        # teeth only in the front of the mouth: towards the corners they recede into the dark
        half, mid_x = 0.5 * (ou[-1, 0] - ou[0, 0]), 0.5 * (ou[-1, 0] + ou[0, 0])
        front = np.clip((0.7 * half - np.abs(gx - mid_x)) / (0.2 * half), 0, 1)
        tc = np.array([0.72, 0.82, 0.88], np.float32) * (0.7 + 0.3 * np.clip(from_top / 3, 0, 1))[..., None]
        tc = tc * (gaps * np.where(teeth_l, 0.8, 1.0))[..., None]
        tmask = ((teeth_u | teeth_l) * front)[..., None]
        col = col * (1 - tmask) + tc * tmask
        # shadows in the lip corners (multiplicative: the lip colour boundary keeps its place)
        for corner in (ou[0], ou[-1]):
            d2 = ((gx - corner[0]) ** 2 + (gy - corner[1]) ** 2) / (2.5 * ppu) ** 2
            roi *= (1 - 0.3 * np.exp(-d2))[..., None]
        mi = _poly_mask(shape, [_closed(iu, il)], org)[..., None]
        roi *= 1 - mi
        roi += mi * col

    def render_canvas(self, curves: dict, weights: np.ndarray, light: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The face of one frame on the model-frame canvas.

        ``curves`` holds one frame of :meth:`FaceModel.curves` (arrays without
        the frame axis), ``weights`` that frame's expression weights and
        ``light`` its unit light direction. Returns the colour (BGR float32,
        not premultiplied) and the coverage (float32 in [0, 1]).
        """
        img = self._albedo.copy()
        alpha, normals = self._alpha, self._n
        # the chin drops with the lower lip (jaw opening)
        il = curves["lip_inner_lower"]
        mid = len(il) // 2
        drop = 0.8 * max(0.0, float(il[mid, 1] - self._neutral["lip_inner_lower"][0, mid, 1]))
        if drop > 0.2:
            y0, y1, x0, x1 = self._jaw_roi
            gx, gy = self._jaw_grid
            mapy = gy - np.float32(drop) * self._jaw_prof
            img[y0:y1, x0:x1] = cv2.remap(self._albedo, gx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            alpha = alpha.copy()
            alpha[y0:y1, x0:x1] = cv2.remap(self._alpha, gx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            normals = normals.copy()
            normals[y0:y1, x0:x1] = cv2.remap(self._n, gx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        raise_w = max(weights[_C["browInnerUp"]], 0.5 * (weights[_C["browOuterUp_L"]] + weights[_C["browOuterUp_R"]]))
        if raise_w > 0.02:
            rows = self._wrinkle_rows
            img[rows] *= (1 - 0.22 * raise_w * self._wrinkles[rows])[..., None]
        self._draw_brow(img, curves["brow_left"], inner_right=True)
        self._draw_brow(img, curves["brow_right"], inner_right=False)
        for k, name in enumerate(("left", "right")):
            self._draw_eye(img, curves[f"eye_{name}_upper"], curves[f"eye_{name}_lower"], curves["iris"][k],
                           self._neutral[f"eye_{name}_upper"][0], light)
        self._draw_folds(img, curves, weights)
        self._draw_mouth(img, curves)
        # shading: wrapped diffuse plus a little specular, from the light direction
        ndl = cv2.transform(normals, np.asarray(light, np.float32).reshape(1, 3))
        diff = np.clip(0.55 * ndl + 0.45, 0, 1)
        shade = 0.28 + 0.95 * diff * diff
        h = np.asarray(light, np.float64) + [0, 0, 1]
        h = (h / np.linalg.norm(h)).astype(np.float32)
        spec = np.clip(cv2.transform(normals, h.reshape(1, 3)), 0, 1)
        spec *= spec
        spec *= spec
        spec *= spec
        spec *= spec
        spec *= spec          # (n.h) ** 32
        cv2.multiply(img, cv2.merge([shade, shade, shade]), dst=img)
        spec *= self._spec_mask
        cv2.add(img, cv2.merge([spec, spec, spec]), dst=img)
        return img, alpha

    def _draw_folds(self, img: np.ndarray, c: dict, weights: np.ndarray) -> None:
        """Nasolabial folds from the nose wings to beside the lip corners, deeper with the smile."""
        ppu = self.ppu
        ou = c["lip_outer_upper"]
        u = np.linspace(0, 1, 12)[:, None]
        for side, corner, smile in ((-1, ou[0], weights[_C["mouthSmile_R"]]), (1, ou[-1], weights[_C["mouthSmile_L"]])):
            A = np.array([side * 15.0, 39.0])
            B = corner + [side * 7.0, 9.0]
            C = np.array([side * (max(abs(A[0]), abs(B[0])) + 5.0), 0.5 * (A[1] + B[1]) - 3.0])
            curve = self._to_canvas((1 - u) ** 2 * A + 2 * u * (1 - u) * C + u ** 2 * B)
            x0, x1, y0, y1 = self._roi(curve, 6 * ppu, 6 * ppu, 6 * ppu)
            m = _poly_mask((y1 - y0, x1 - x0), [curve], (x0, y0), closed=False, thickness=round(2 * ppu))
            m = cv2.GaussianBlur(m, (0, 0), 1.8 * ppu)
            img[y0:y1, x0:x1] *= (1 - (0.12 + 0.25 * smile) * m)[..., None]

    def composite(self, canvas: np.ndarray, alpha: np.ndarray, pose: np.ndarray, shift_px: np.ndarray,
                  exposure: float, blur_vec: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Warp ``canvas`` with coverage ``alpha`` into the frame with ``pose`` (image_from_model), add
        background, torso and camcorder degradations; return BGR uint8.

        ``shift_px`` moves the torso (the head's translation in pixels),
        ``blur_vec`` is the image motion during the exposure (pixels) for the
        motion blur, ``rng`` draws the sensor noise.
        """
        W, H = self.size
        M = _compose(pose, _affine_inv(self.canvas_from_model))
        ch, cw = self.canvas_shape
        corners = np.array([[0, 0], [cw, 0], [0, ch], [cw, ch]], float) @ M[:, :2].T + M[:, 2]
        L = float(np.hypot(*blur_vec))
        pad = int(np.ceil(L)) + 3
        x0 = int(max(np.floor(corners[:, 0].min()) - pad, 0))
        x1 = int(min(np.ceil(corners[:, 0].max()) + pad, W))
        y0 = int(max(np.floor(corners[:, 1].min()) - pad, 0))
        y1 = int(min(np.ceil(corners[:, 1].max()) + pad, H))
        frame = self._background.copy()
        if x1 > x0 and y1 > y0:
            Mr = M.copy()
            Mr[:, 2] -= (x0, y0)
            pm = cv2.multiply(canvas, cv2.merge([alpha, alpha, alpha]))
            dsize = (x1 - x0, y1 - y0)
            pm = cv2.warpAffine(pm, Mr, dsize, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            a = cv2.warpAffine(alpha, Mr, dsize, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=0)
            if L >= 1.0:
                ker = _motion_kernel(blur_vec)
                pm = cv2.filter2D(pm, -1, ker, borderType=cv2.BORDER_CONSTANT)
                a = cv2.filter2D(a, -1, ker, borderType=cv2.BORDER_CONSTANT)
            _over(frame[y0:y1, x0:x1], pm, a)
        T = np.array([[1, 0, shift_px[0]], [0, 1, shift_px[1]]], np.float64)
        dsize = (W, H - self._torso_top)
        tpm = cv2.warpAffine(self._torso_pm, T, dsize, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        ta = cv2.warpAffine(self._torso_a, T, dsize, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        _over(frame[self._torso_top:], tpm, ta)
        cv2.multiply(frame, self._vignette, dst=frame, scale=float(exposure))
        frame = cv2.GaussianBlur(frame, (5, 5), 0.35 + 0.35 * self.model_scale)
        # sensor noise: a random crop of a fixed noise field chosen by the frame's rng
        nh, nw = self._noise.shape[:2]
        ya, xa = rng.integers(0, nh - H + 1), rng.integers(0, nw - W + 1)
        cv2.add(frame, self._noise[ya:ya + H, xa:xa + W], dst=frame)
        return cv2.convertScaleAbs(frame, alpha=255.0)


def _over(dst: np.ndarray, pm: np.ndarray, alpha: np.ndarray) -> None:
    """Composite premultiplied colour ``pm`` with coverage ``alpha`` over ``dst`` in place."""
    a3 = cv2.merge([alpha, alpha, alpha])
    np.subtract(np.float32(1.0), a3, out=a3)
    cv2.multiply(dst, a3, dst=dst)
    cv2.add(dst, pm, dst=dst)


def _motion_kernel(vec: np.ndarray) -> np.ndarray:
    """Normalised line kernel of the motion ``vec`` (pixels) during the exposure."""
    L = float(np.hypot(*vec))
    k = int(np.ceil(L)) | 1
    k = max(k + 2, 3)
    ker = np.zeros((k, k), np.float32)
    n = max(int(4 * L), 2)
    s = np.linspace(-0.5, 0.5, n)
    xs = (k - 1) / 2 + s * vec[0]
    ys = (k - 1) / 2 + s * vec[1]
    xi, yi = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - xi, ys - yi
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(ker, (np.clip(yi + dy, 0, k - 1), np.clip(xi + dx, 0, k - 1)), w)
    return ker / ker.sum()
