"""Render one frame of the synthetic face: model-frame canvas, head pose warp, camcorder degradations.

The face is drawn on a **canvas** in the model frame (``canvas_from_model``:
a fixed scale and offset), then warped into the image with the frame's head
pose (``image_from_model``) by one ``cv2.warpAffine``. Everything that does not
change per frame is precomputed once in :class:`FaceRenderer`: the skin albedo
with its noise texture (fixed per seed, moving with the face), the surface
normals for the drifting light, the hair, ears and neck, the alpha matte, the
background room, the torso layer and the vignette. Per frame only the moving
features are drawn, each inside its own small region of interest: brows
(polygons around the brow spine), eyes (lash line, lid crease, then sclera,
iris and pupil computed analytically on the eye's pixel grid and clipped by
the lid polygon), lips (outer lip polygon, dark mouth interior with teeth and
tongue inside the inner lip polygon).

Pixel convention: OpenCV's, pixel centres at integer coordinates, for the
polygons (``cv2.fillPoly`` with 4 fractional bits and anti-aliasing), the
analytic iris and pupil discs and the warp, so the ``contours48`` points
computed from the same curves lie on the drawn edges to sub-pixel accuracy.
"""
from __future__ import annotations

import cv2
import numpy as np

from data_synth.face_model import COMPONENTS, FaceModel
from data_synth.performance import Performance

_SHIFT = 4
_ONE = 1 << _SHIFT
_C = {name: k for k, name in enumerate(COMPONENTS)}

_SKIN = np.array([[0.56, 0.66, 0.86], [0.45, 0.57, 0.78], [0.33, 0.44, 0.63], [0.62, 0.71, 0.88],
                  [0.50, 0.62, 0.84]])
_HAIR = np.array([[0.07, 0.08, 0.10], [0.10, 0.16, 0.24], [0.20, 0.32, 0.45], [0.05, 0.05, 0.06]])
_IRIS = np.array([[0.10, 0.22, 0.36], [0.55, 0.42, 0.25], [0.30, 0.42, 0.28], [0.08, 0.14, 0.22]])
_LIP = np.array([[0.36, 0.36, 0.66], [0.40, 0.40, 0.72], [0.30, 0.30, 0.55]])
_SHIRT = np.array([[0.45, 0.25, 0.12], [0.20, 0.20, 0.22], [0.55, 0.55, 0.50], [0.15, 0.30, 0.50]])


def _noise(shape, sigma, rng, gen=None) -> np.ndarray:
    """Smooth noise of unit standard deviation: white noise blurred with ``sigma`` pixels."""
    x = rng.standard_normal(shape).astype(np.float32)
    if sigma > 0.3:
        x = cv2.GaussianBlur(x, (0, 0), sigma)
    return x / max(float(x.std()), 1e-6)


def _poly_mask(shape, polys, origin=(0.0, 0.0), closed=True, thickness: int | None = None) -> np.ndarray:
    """Anti-aliased coverage in [0, 1] of polygons (or polylines of ``thickness`` px) on a grid of ``shape``."""
    m = np.zeros(shape, np.uint8)
    pts = [np.round((np.asarray(p) - origin) * _ONE).astype(np.int32).reshape(-1, 1, 2) for p in polys]
    if thickness is None:
        cv2.fillPoly(m, pts, 255, cv2.LINE_AA, _SHIFT)
    else:
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
        a = 112.0 * (1 - 0.28 * np.clip((Y - 10) / 140, 0, 1) ** 1.6)
        f_head = (X / a) ** 2 + ((Y + 5) / 150.0) ** 2
        head = f_head < 1
        f_neck = np.abs(X) / (50.0 + 0.25 * np.clip(Y - 150, 0, None))
        neck = (f_neck < 1) & (Y > 40)
        ears = [((X - s * 110) / 13.0) ** 2 + ((Y + 2) / 27.0) ** 2 < 1 for s in (-1, 1)]
        # height field for the normals
        hgt = 95.0 * np.sqrt(np.clip(1 - f_head, 0, 1))
        hgt = hgt + 14 * g(0, 5, 6.5, 32) * (Y < 40) + 10 * g(0, 36, 8, 8) + 5 * g(-12, 41, 6, 5) + 5 * g(12, 41, 6, 5)
        hgt = hgt + 5 * g(0, -52, 70, 8) - 7 * g(-47, -28, 22, 13) - 7 * g(47, -28, 22, 13)
        hgt = hgt + 4 * g(-47, -28, 11, 8) + 4 * g(47, -28, 11, 8) + 6 * g(-60, 12, 22, 18) + 6 * g(60, 12, 22, 18)
        hgt = hgt + 6 * g(0, 80, 28, 11) + 6 * g(0, 132, 18, 14) - 3 * g(0, 106, 16, 5)
        neck_h = 60.0 * np.sqrt(np.clip(1 - f_neck ** 2, 0, 1)) - 25
        hgt = np.where(head, hgt, np.where(neck, neck_h, 0.0))
        for e in ears:
            hgt = np.where(e & ~head, 30.0, hgt)
        hgt = cv2.GaussianBlur(hgt.astype(np.float32), (0, 0), 1.2 * ppu)
        gy, gx = np.gradient(hgt, 1.0 / ppu)
        nz = np.ones_like(gx)
        norm = np.sqrt(gx ** 2 + gy ** 2 + 1)
        self._n = np.stack([-gx / norm, -gy / norm, nz / norm]).astype(np.float32)   # (3, h, w)
        # albedo: skin with multi-scale texture
        tex = (1 + 0.05 * _noise(X.shape, 9 * ppu, rng) + 0.03 * _noise(X.shape, 2.5 * ppu, rng)
               + 0.025 * _noise(X.shape, 0.6 * ppu, rng))
        red = 0.05 * _noise(X.shape, 14 * ppu, rng)
        albedo = np.empty(X.shape + (3,), np.float32)
        for c in range(3):
            albedo[..., c] = self.skin[c] * tex
        albedo[..., 2] *= 1 + red
        albedo[..., 1] *= 1 - 0.4 * red
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
        f_hair = (X / 126.0) ** 2 + ((Y + 18) / 170.0) ** 2
        strands = rng.standard_normal(X.shape).astype(np.float32)
        strands = cv2.GaussianBlur(strands, (0, 0), sigmaX=0.7 * ppu, sigmaY=7 * ppu)
        strands /= strands.std()
        edge_noise = 3.0 * _noise(X.shape, 3 * ppu, rng)
        hair = (f_hair < 1 + edge_noise * 0.01) & (Y < hairline + edge_noise) & (Y < 20)
        hair_tex = (1 + 0.22 * strands + 0.1 * _noise(X.shape, 12 * ppu, rng)) * (0.8 + 0.2 * np.clip(-Y / 150, 0, 1))
        for c in range(3):
            albedo[..., c] = np.where(hair, self.hair[c] * hair_tex, albedo[..., c])
        # forehead wrinkles (shown with the brow raise)
        wr = np.zeros(X.shape, np.float32)
        for k, y0 in enumerate((-72, -80, -88)):
            yy = y0 + 3 * np.sin(X / 25.0 + k)
            wr += np.exp(-((Y - yy) / 0.9) ** 2) * np.exp(-(X / 55.0) ** 4)
        self._wrinkles = wr
        self._hair_mask = hair
        mask = (head | neck | ears[0] | ears[1] | hair).astype(np.float32)
        self._alpha = cv2.GaussianBlur(mask, (0, 0), 0.6 * ppu)
        self._albedo = albedo
        self._strands = strands
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
        # furniture: a door frame, a shelf, a picture and a lamp glow, out of focus
        for _ in range(int(rng.integers(3, 6))):
            w, h = rng.uniform(0.08, 0.3) * W, rng.uniform(0.1, 0.6) * H
            x0 = rng.choice([rng.uniform(0, 0.25), rng.uniform(0.62, 0.92)]) * W
            y0 = rng.uniform(0, 0.7) * H
            col = rng.uniform(0.1, 0.8, 3).astype(np.float32)
            m = ((xs > x0) & (xs < x0 + w) & (ys > y0) & (ys < y0 + h)).astype(np.float32)
            bg = bg * (1 - 0.8 * m[..., None]) + 0.8 * m[..., None] * col
        lamp = np.exp(-(((xs - rng.uniform(0, W)) / (0.2 * W)) ** 2 + ((ys - 0.15 * H) / (0.2 * H)) ** 2))
        bg += 0.25 * lamp[..., None].astype(np.float32)
        self._background = cv2.GaussianBlur(bg, (0, 0), 2.5 * s)
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
        self._torso_pm = (col * m[..., None]).astype(np.float32)
        self._torso_a = m.astype(np.float32)
        r = np.hypot((xs - W / 2) / W, (ys - H / 2) / H)
        self._vignette = (1 - 0.35 * r ** 2)[..., None].astype(np.float32)

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
        th = (7.5 - 4.5 * v ** 1.2) * ppu
        d = np.gradient(sp, axis=0)
        nrm = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.linalg.norm(d, axis=1, keepdims=True)
        top = sp - nrm * (th[:, None] / 2)
        bot = sp + nrm * (th[:, None] / 2)
        poly = np.concatenate([top, bot[::-1]])
        x0, x1, y0, y1 = self._roi(poly, 2, 2, 2)
        m = _poly_mask((y1 - y0, x1 - x0), [poly], (x0, y0))
        hairy = np.clip(0.75 + 0.35 * self._strands[y0:y1, x0:x1], 0, 1)
        m = m * hairy
        roi = img[y0:y1, x0:x1]
        roi *= (1 - 0.85 * m)[..., None]
        roi += (0.85 * m)[..., None] * self.hair

    def _draw_eye(self, img: np.ndarray, upper: np.ndarray, lower: np.ndarray, iris: np.ndarray,
                  neutral_upper: np.ndarray, light: np.ndarray, side: int) -> None:
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
        lm = _poly_mask(shape, [lo + [0, 0.8 * ppu]], org, closed=False, thickness=round(1.5 * ppu))
        roi *= (1 - 0.25 * lm)[..., None]
        # lash line just above the upper lid edge (the eye interior is drawn over its lower half)
        lash = _poly_mask(shape, [up - [0, 0.6 * ppu]], org, closed=False, thickness=round(2.6 * ppu))
        roi *= (1 - 0.9 * lash)[..., None]
        roi += (0.9 * lash)[..., None] * (0.3 * self.hair)
        # eye interior on the ROI grid
        gx = np.arange(x0, x1, dtype=np.float32)[None, :]
        gy = np.arange(y0, y1, dtype=np.float32)[:, None]
        yu = np.interp(gx[0], up[:, 0], up[:, 1]).astype(np.float32)[None, :]
        below_lid = (gy - yu) / ppu
        xc = (gx - (up[0, 0] + up[-1, 0]) / 2) / (up[-1, 0] - up[0, 0]) * 2
        sclera = np.array([0.80, 0.84, 0.88], np.float32) * (
            (1 - 0.45 * np.exp(-np.clip(below_lid, 0, None) / 2.2)) * (1 - 0.25 * xc ** 4))[..., None]
        dx, dy = gx - ic[0], gy - ic[1]
        r = np.sqrt(dx * dx + dy * dy) / ppu
        R, Rp = self.model.iris_radius, self.model.pupil_radius
        ang = np.arctan2(dy, dx)
        streak = 1 + 0.07 * (np.sin(7 * ang + self.iris_phase[0]) + np.sin(13 * ang + self.iris_phase[1])
                             + np.sin(23 * ang + self.iris_phase[2]) + np.sin(37 * ang + self.iris_phase[3]))
        radial = 0.75 + 0.45 * np.exp(-((r - 1.5 * Rp) / 2.0) ** 2) - 0.45 * np.clip((r - 0.8 * R) / (0.2 * R), 0, 1)
        iris = self.iris[None, None, :].astype(np.float32) * (streak * radial)[..., None]
        iris *= (1 - 0.4 * np.exp(-np.clip(below_lid, 0, None) / 2.5))[..., None]
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
        tc = np.array([0.78, 0.86, 0.88], np.float32)
        col = np.where((teeth_u | teeth_l)[..., None], tc * (gaps * np.where(teeth_l, 0.8, 1.0))[..., None], col)
        mi = _poly_mask(shape, [_closed(iu, il)], org)[..., None]
        roi *= 1 - mi
        roi += mi * col

    def render_canvas(self, curves: dict, weights: np.ndarray, light: np.ndarray) -> np.ndarray:
        """The face of one frame on the model-frame canvas: BGR float32 in [0, ~1.2], not yet premultiplied.

        ``curves`` holds one frame of :meth:`FaceModel.curves` (arrays without
        the frame axis), ``weights`` that frame's expression weights and
        ``light`` its unit light direction.
        """
        img = self._albedo.copy()
        raise_w = max(weights[_C["browInnerUp"]], 0.5 * (weights[_C["browOuterUp_L"]] + weights[_C["browOuterUp_R"]]))
        if raise_w > 0.02:
            rows = self._wrinkle_rows
            img[rows] *= (1 - 0.22 * raise_w * self._wrinkles[rows])[..., None]
        self._draw_brow(img, curves["brow_left"], inner_right=True)
        self._draw_brow(img, curves["brow_right"], inner_right=False)
        for k, name in enumerate(("left", "right")):
            self._draw_eye(img, curves[f"eye_{name}_upper"], curves[f"eye_{name}_lower"], curves["iris"][k],
                           self._neutral[f"eye_{name}_upper"][0], light, k)
        self._draw_mouth(img, curves)
        # shading: wrapped diffuse plus a little specular, from the light direction
        n = self._n
        ndl = n[0] * np.float32(light[0]) + n[1] * np.float32(light[1]) + n[2] * np.float32(light[2])
        diff = np.clip(0.55 * ndl + 0.45, 0, 1)
        shade = 0.28 + 0.95 * diff * diff
        h = np.asarray(light, np.float64) + [0, 0, 1]
        h = h / np.linalg.norm(h)
        ndh = np.clip(n[0] * np.float32(h[0]) + n[1] * np.float32(h[1]) + n[2] * np.float32(h[2]), 0, 1)
        spec = ndh * ndh
        spec *= spec
        spec *= spec
        spec *= spec
        spec *= spec          # ndh ** 32
        img *= shade[..., None]
        img += (0.12 * spec * (1 - self._hair_mask))[..., None]
        return img

    def composite(self, canvas: np.ndarray, pose: np.ndarray, shift_px: np.ndarray, exposure: float,
                  blur_vec: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Warp ``canvas`` into the frame with ``pose`` (image_from_model), add background, torso and
        camcorder degradations; return BGR uint8.

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
            rgba = np.dstack([canvas * self._alpha[..., None], self._alpha])
            warped = cv2.warpAffine(rgba, Mr, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            if L >= 1.0:
                warped = cv2.filter2D(warped, -1, _motion_kernel(blur_vec), borderType=cv2.BORDER_CONSTANT)
            roi = frame[y0:y1, x0:x1]
            roi *= 1 - warped[..., 3:4]
            roi += warped[..., :3]
        T = np.array([[1, 0, shift_px[0]], [0, 1, shift_px[1]]], np.float64)
        tpm = cv2.warpAffine(np.dstack([self._torso_pm, self._torso_a]), T, (W, H), flags=cv2.INTER_LINEAR)
        frame *= 1 - tpm[..., 3:4]
        frame += tpm[..., :3]
        frame *= self._vignette * np.float32(exposure)
        frame = cv2.GaussianBlur(frame, (0, 0), 0.35 + 0.35 * self.model_scale)
        frame += rng.standard_normal(frame.shape, dtype=np.float32) * np.float32(0.013)
        return np.clip(frame * 255.0 + 0.5, 0, 255).astype(np.uint8)


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
