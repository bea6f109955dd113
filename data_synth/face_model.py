"""The 2D feature geometry of the synthetic face as a function of hidden expression weights.

Design notes and figures: docs/synth.md, "Notes on the code", ``data_synth/face_model.py``.
"""
from __future__ import annotations

import numpy as np

from keyshape.base.errors import InputError

#: The hidden expression components, in the column order of the weights.
COMPONENTS: tuple[str, ...] = (
    "jawOpen", "mouthSmile_L", "mouthSmile_R", "mouthPucker", "mouthFunnel",
    "eyeBlink_L", "eyeBlink_R", "browInnerUp", "browOuterUp_L", "browOuterUp_R",
)
N_COMPONENTS = len(COMPONENTS)
#: Dense samples per curve (per half of a closed contour).
N_SAMPLES = 48

_C = {name: k for k, name in enumerate(COMPONENTS)}


def _param(base: float, **coef: float) -> np.ndarray:
    """A geometry parameter as an affine function of the weights: ``[base, c_0 .. c_{K-1}]``."""
    v = np.zeros(N_COMPONENTS + 1)
    v[0] = base
    for name, c in coef.items():
        v[1 + _C[name]] = c
    return v


def resample_by_arc_length(curves: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Points at given fractions of arc length along polylines, for many polylines at once.

    Parameters
    ----------
    curves : (n, n_samples, 2) polylines
    fractions : (m,) values in [0, 1]; 0 is the first vertex, 1 the last.

    Returns
    -------
    (n, m, 2) points on the polylines (linear interpolation between vertices,
    so each point lies exactly on the drawn polyline).
    """
    seg = np.linalg.norm(np.diff(curves, axis=1), axis=-1)                  # (n, N-1)
    s = np.concatenate([np.zeros((len(curves), 1)), np.cumsum(seg, axis=1)], axis=1)  # (n, N)
    target = np.asarray(fractions, dtype=np.float64)[None, :] * s[:, -1:]    # (n, m)
    # segment index: number of interior knots at or before the target
    idx = (s[:, None, 1:-1] <= target[:, :, None]).sum(axis=-1)              # (n, m) in [0, N-2]
    s0 = np.take_along_axis(s, idx, axis=1)
    s1 = np.take_along_axis(s, idx + 1, axis=1)
    a = np.clip((target - s0) / np.maximum(s1 - s0, 1e-12), 0.0, 1.0)[..., None]
    p0 = np.take_along_axis(curves, idx[..., None], axis=1)
    p1 = np.take_along_axis(curves, idx[..., None] + 1, axis=1)
    return p0 * (1 - a) + p1 * a


def closed_contour_points(upper: np.ndarray, lower: np.ndarray, n_points: int) -> np.ndarray:
    """The ``contours48`` points of a closed contour from its upper and lower curves.

    Both curves run from the image-left corner to the image-right corner. The
    result starts at the image-left corner, runs along the upper curve to the
    image-right corner, then back along the lower curve; the points between the
    corners are spaced evenly by arc length on each curve.
    """
    m = (n_points - 2) // 2
    f = np.linspace(0.0, 1.0, m + 2)
    up = resample_by_arc_length(upper, f)                      # corners + m
    lo = resample_by_arc_length(lower, f[1:-1])[:, ::-1]       # m, right to left
    return np.concatenate([up, lo], axis=1)


class FaceModel:
    """Feature curves and ``contours48`` landmarks of one synthetic face.

    Parameters
    ----------
    rng : None, int or numpy.random.Generator
        Draws the face's proportions (eye spacing, mouth width, lip thickness,
        brow arch: a few percent around the mean face), fixed for a seed.

    Attributes
    ----------
    components : tuple of str
        Names of the hidden expression components (``COMPONENTS``).
    eye_centres : (2, 2) model-frame centres of the image-left and image-right eyes.
    mouth_centre : (2,) model-frame mouth centre.
    iris_radius, pupil_radius : float, model units.
    gaze_range : (2,) iris travel in model units for gaze (+-1, +-1).
    """

    components = COMPONENTS

    def __init__(self, rng=None):
        rng = np.random.default_rng(rng)
        j = lambda s: 1.0 + s * rng.uniform(-1, 1)  # noqa: E731  (proportion jitter)
        self.eye_dx = 47.0 * j(0.05)
        self.eye_y = -28.0 * j(0.05)
        self.eye_hw = 23.0 * j(0.05)
        self.eye_centres = np.array([[-self.eye_dx, self.eye_y], [self.eye_dx, self.eye_y]])
        self.mouth_centre = np.array([0.0, 78.0 * j(0.04)])
        self.iris_radius = 10.5 * j(0.04)
        self.pupil_radius = 3.8 * j(0.08)
        self.gaze_range = np.array([8.0, 3.5])
        self.brow_gap = 25.0 * j(0.08)
        self.brow_arch = 7.0 * j(0.2)
        mw, ut, lt = 38.0 * j(0.06), 9.5 * j(0.12), 11.0 * j(0.12)
        # geometry parameters, each an affine function of the weights: [base, per-component coefficients]
        P = {}
        for side, s, smile, blink, outer in (("l", -1, "mouthSmile_R", "eyeBlink_R", "browOuterUp_R"),
                                            ("r", +1, "mouthSmile_L", "eyeBlink_L", "browOuterUp_L")):
            # eye: upper lid height above the corner line, lower lid depth below it
            P[f"eye_up_{side}"] = _param(10.0, **{blink: -15.0, smile: -1.0, outer: 1.0})  # shut at 1: meets the lower lid
            P[f"eye_lo_{side}"] = _param(6.5, **{blink: -1.2, smile: -2.2})
            # brow: rise of the inner and outer ends
            P[f"brow_in_{side}"] = _param(0.0, browInnerUp=9.0, **{blink: -1.5})
            P[f"brow_out_{side}"] = _param(0.0, browInnerUp=1.5, **{outer: 9.0, blink: -1.0})
            # lip corner x (outwards positive) and y (down positive), relative to the neutral corner
            P[f"corner_x_{side}"] = _param(mw, **{smile: 7.0}, mouthPucker=-11.0, mouthFunnel=-8.0, jawOpen=-2.0)
            P[f"corner_y_{side}"] = _param(0.0, **{smile: -8.0}, jawOpen=5.0, mouthFunnel=1.0)
        P["up_outer"] = _param(ut, mouthPucker=3.0, mouthFunnel=3.0, mouthSmile_L=-1.0, mouthSmile_R=-1.0)
        P["up_inner"] = _param(0.6, jawOpen=-3.0, mouthFunnel=-3.0, mouthSmile_L=-1.0, mouthSmile_R=-1.0)
        P["open_jaw"] = _param(0.4, jawOpen=26.0, mouthSmile_L=1.0, mouthSmile_R=1.0)
        P["open_funnel"] = _param(0.0, mouthFunnel=11.0)
        P["lo_thick"] = _param(lt, mouthPucker=3.0, mouthFunnel=2.0, mouthSmile_L=1.0, mouthSmile_R=1.0,
                               jawOpen=-1.0)
        P["lip_bend"] = _param(0.0, mouthSmile_L=1.5, mouthSmile_R=1.5)
        self._param_names = list(P)
        self._param_matrix = np.stack([P[k] for k in self._param_names])     # (n_params, 1 + K)
        self._u = np.linspace(0.0, 1.0, N_SAMPLES)
        self.inner_inset = 2.5
        self.bow_depth = 2.0

    # ------------------------------------------------------------------ parameters
    def _params(self, weights: np.ndarray) -> dict[str, np.ndarray]:
        w = np.asarray(weights, dtype=np.float64)
        vals = np.concatenate([np.ones((len(w), 1)), w], axis=1) @ self._param_matrix.T   # (n, n_params)
        return {k: vals[:, i] for i, k in enumerate(self._param_names)}

    @staticmethod
    def check_weights(weights, gaze=None) -> tuple[np.ndarray, np.ndarray]:
        """Validate ``weights`` (n_frames, n_components) and ``gaze`` (n_frames, 2); return float64 copies."""
        w = np.asarray(weights, dtype=np.float64)
        if w.ndim == 1:
            w = w[None]
        if w.ndim != 2 or w.shape[1] != N_COMPONENTS:
            raise InputError(f"weights: expected shape (n_frames, {N_COMPONENTS}), got {w.shape}")
        g = np.zeros((len(w), 2)) if gaze is None else np.asarray(gaze, dtype=np.float64).reshape(len(w), 2)
        if not (np.isfinite(w).all() and np.isfinite(g).all()):
            raise InputError("weights/gaze contain NaN or infinity")
        return w, g

    # ------------------------------------------------------------------ curves
    def curves(self, weights, gaze=None) -> dict[str, np.ndarray]:
        """Dense feature curves in the model frame, each ``(n_frames, N_SAMPLES, 2)``.

        Keys: ``brow_left``/``brow_right`` (spines, image-left to image-right),
        ``eye_left_upper``/``_lower``, ``eye_right_upper``/``_lower``,
        ``lip_outer_upper``/``_lower``, ``lip_inner_upper``/``_lower`` (each
        from the image-left corner to the image-right corner), and
        ``iris`` ``(n_frames, 2, 2)``: iris centres of the image-left and
        image-right eyes (the pupils).
        """
        w, g = self.check_weights(weights, gaze)
        p = self._params(w)
        u = self._u[None, :]                       # (1, N)
        n = len(w)
        out: dict[str, np.ndarray] = {}
        bump = lambda q: np.sin(np.pi * u) ** q  # noqa: E731
        for side, (cx, cy) in zip("lr", self.eye_centres):
            name = "left" if side == "l" else "right"
            inner = +1 if side == "l" else -1      # direction of the nose along x
            # corners: outer corner slightly higher (canthal tilt)
            x = cx + (2 * u - 1) * self.eye_hw
            line = cy + 1.5 * inner * (2 * u - 1)
            # upper lid peaks a little towards the inner side
            skew = np.sin(np.pi * (u if inner > 0 else 1 - u) ** 1.15) ** 0.85
            up_a = p[f"eye_up_{side}"][:, None]
            lo_a = p[f"eye_lo_{side}"][:, None]
            up_a = np.maximum(up_a, -lo_a + 0.3)   # a closed lid meets the lower lid, never crosses it
            upper = np.stack(np.broadcast_arrays(x + 0 * up_a, line - up_a * skew), axis=-1)
            lower = np.stack(np.broadcast_arrays(x + 0 * lo_a, line + lo_a * bump(0.9)), axis=-1)
            out[f"eye_{name}_upper"] = upper
            out[f"eye_{name}_lower"] = lower
            # brow spine from image-left end to image-right end; v = 0 at the inner end
            v = (1 - u) if inner > 0 else u
            bx = cx + inner * (24.0 - 51.0 * v) * np.ones((n, 1))
            by = (cy - self.brow_gap - self.brow_arch * np.sin(np.pi * np.clip(v / 1.3, 0, 1)) * 1.0
                  + 3.0 * v ** 2
                  - p[f"brow_in_{side}"][:, None] * (1 - v) ** 1.3 - p[f"brow_out_{side}"][:, None] * v ** 1.3)
            out[f"brow_{name}"] = np.stack(np.broadcast_arrays(bx, by), axis=-1)
        # mouth
        mx, my = self.mouth_centre
        xl = mx - p["corner_x_l"][:, None]
        xr = mx + p["corner_x_r"][:, None]
        yl = my + p["corner_y_l"][:, None]
        yr = my + p["corner_y_r"][:, None]
        x_out = xl + (xr - xl) * u
        line = yl + (yr - yl) * u + p["lip_bend"][:, None] * bump(1.0)
        ins = self.inner_inset
        x_in = xl + ins + (xr - xl - 2 * ins) * u
        bow = self.bow_depth * np.exp(-((u - 0.5) / 0.07) ** 2)
        ellipse = 2 * np.sqrt(np.clip(u * (1 - u), 0, None))
        out["lip_outer_upper"] = np.stack([x_out, line - p["up_outer"][:, None] * bump(0.55) + bow], axis=-1)
        inner_up = line + p["up_inner"][:, None] * bump(0.8)
        inner_lo = inner_up + p["open_jaw"][:, None] * bump(0.8) + p["open_funnel"][:, None] * ellipse
        out["lip_inner_upper"] = np.stack([x_in, inner_up], axis=-1)
        out["lip_inner_lower"] = np.stack([x_in, inner_lo], axis=-1)
        outer_lo = (line + p["up_inner"][:, None] * bump(0.8) + p["open_jaw"][:, None] * bump(0.8)
                    + p["open_funnel"][:, None] * ellipse + p["lo_thick"][:, None] * bump(0.6))
        out["lip_outer_lower"] = np.stack([x_out, outer_lo], axis=-1)
        # pupils: midpoint of the eye corners plus gaze
        iris = self.eye_centres[None, :, :] + (g * self.gaze_range)[:, None, :]
        out["iris"] = iris
        return out

    # ------------------------------------------------------------------ landmarks
    def landmarks(self, weights, gaze=None, curves: dict | None = None) -> np.ndarray:
        """``contours48`` landmarks in the model frame, ``(n_frames, 48, 2)``.

        Brows: 5 points evenly by arc length along the spine, image-left to
        image-right. Eyes (8 points) and lips (12 outer, 8 inner): from the
        image-left corner along the upper curve to the image-right corner,
        then back along the lower curve, evenly by arc length between the
        corners. Pupils: the iris centres.
        """
        c = self.curves(weights, gaze) if curves is None else curves
        f5 = np.linspace(0, 1, 5)
        parts = [resample_by_arc_length(c["brow_left"], f5), resample_by_arc_length(c["brow_right"], f5),
                 closed_contour_points(c["eye_left_upper"], c["eye_left_lower"], 8),
                 closed_contour_points(c["eye_right_upper"], c["eye_right_lower"], 8),
                 c["iris"],
                 closed_contour_points(c["lip_outer_upper"], c["lip_outer_lower"], 12),
                 closed_contour_points(c["lip_inner_upper"], c["lip_inner_lower"], 8)]
        return np.concatenate(parts, axis=1)

    def basis(self) -> tuple[np.ndarray, np.ndarray]:
        """The neutral shape ``(48, 2)`` and each component's landmark displacement at weight 1, ``(K, 48, 2)``.

        The landmarks are linear in the weights up to the arc-length
        resampling (and the lid-closure clamp), so ``neutral + weights @ basis``
        reproduces them to a fraction of a model unit (``linear_residual``).
        """
        w = np.vstack([np.zeros(N_COMPONENTS), np.eye(N_COMPONENTS)])
        pts = self.landmarks(w)
        return pts[0], pts[1:] - pts[0]

    def linear_residual(self, weights, gaze=None) -> float:
        """Largest distance (model units) between the landmarks and their linear model ``neutral + w @ basis``."""
        w, g = self.check_weights(weights, gaze)
        neutral, basis = self.basis()
        lin = neutral + np.einsum("nk,kpd->npd", w, basis)
        lm = self.landmarks(w, np.zeros_like(g))
        return float(np.linalg.norm(lm - lin, axis=-1).max())
