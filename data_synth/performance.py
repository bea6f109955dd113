"""A talking performance for a seed: expression weights, gaze, blinks, head pose, light and exposure per frame.

Design notes and figures: docs/synth.md, "Notes on the code", ``data_synth/performance.py``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from keyshape.data_synth.face_model import COMPONENTS

_C = {name: k for k, name in enumerate(COMPONENTS)}


@dataclass
class Performance:
    """Per-frame hidden state of a synthetic performance.

    Attributes
    ----------
    weights : (n_frames, n_components) expression weights in [0, 1], columns named by ``COMPONENTS``.
    gaze : (n_frames, 2) gaze in [-1, 1] (x to the image-right, y down).
    roll_deg, scale : (n_frames,) head roll (degrees) and scale factor about 1.
    shift : (n_frames, 2) head translation in model units, added to the base head position.
    light : (n_frames, 3) unit light direction in the model frame (x right, y down, z to the camera).
    exposure : (n_frames,) camera gain about 1.
    fps : float
    """

    weights: np.ndarray
    gaze: np.ndarray
    roll_deg: np.ndarray
    scale: np.ndarray
    shift: np.ndarray
    light: np.ndarray
    exposure: np.ndarray
    fps: float

    @property
    def n_frames(self) -> int:
        return len(self.weights)


def smooth_noise(n: int, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian-filtered white noise of unit standard deviation (in expectation), length ``n``."""
    sigma = max(float(sigma), 0.5)
    pad = int(4 * sigma) + 1
    x = gaussian_filter1d(rng.standard_normal(n + 2 * pad), sigma, mode="wrap")[pad:pad + n]
    return x * np.sqrt(2 * np.sqrt(np.pi) * sigma)


def pulse(t: np.ndarray, t0: float, dur: float, attack: float) -> np.ndarray:
    """A plateau from ``t0`` lasting ``dur`` with raised-cosine attack and release of ``attack`` seconds."""
    a = np.clip((t - t0) / attack, 0, 1)
    b = np.clip((t0 + dur - t) / attack, 0, 1)
    return np.sin(0.5 * np.pi * np.minimum(a, b)) ** 2


def _events(total: float, mean_gap: float, rng: np.random.Generator, start: float = 0.0) -> np.ndarray:
    """Event times of a renewal process with gaps ~ uniform(0.4, 1.6) * mean_gap."""
    n = int(total / mean_gap * 2) + 4
    times = start + np.cumsum(rng.uniform(0.4, 1.6, n) * mean_gap)
    return times[times < total]


def make_performance(n_frames: int, fps: float = 30.0, rng=None) -> Performance:
    """Draw a talking performance of ``n_frames`` frames at ``fps``.

    Parameters
    ----------
    n_frames : int
    fps : float
    rng : None, int or numpy.random.Generator

    Returns
    -------
    Performance
    """
    rng = np.random.default_rng(rng)
    r_speech, r_expr, r_blink, r_gaze, r_head, r_light = rng.spawn(6)
    t = np.arange(n_frames) / fps
    total = n_frames / fps
    W = np.zeros((n_frames, len(COMPONENTS)))

    # --- speech: phrases of syllables at 4-5 Hz separated by pauses
    jaw, funnel, pucker, stretch = (np.zeros(n_frames) for _ in range(4))
    now = r_speech.uniform(0.0, 0.4)
    while now < total:
        n_syll = int(r_speech.integers(4, 13))
        for _ in range(n_syll):
            d = r_speech.uniform(0.18, 0.26)
            kind = r_speech.choice(4, p=[0.55, 0.17, 0.13, 0.15])
            env = pulse(t, now, d, d * 0.5)
            amp = r_speech.uniform(0.25, 1.0) ** 0.8
            if kind == 0:      # open vowel
                jaw += amp * env
            elif kind == 1:    # rounded vowel "o"
                funnel += amp * env
                jaw += 0.35 * amp * env
            elif kind == 2:    # "u": pucker, mouth nearly shut
                pucker += amp * pulse(t, now - 0.04, d + 0.08, d * 0.5)
                jaw += 0.08 * env
            else:              # "i/e": spread lips, half open
                stretch += amp * env
                jaw += 0.45 * amp * env
            now += d
        now += r_speech.uniform(0.25, 0.9)
    sm = lambda x: gaussian_filter1d(x, 0.6 * fps / 30.0, mode="nearest")  # noqa: E731  coarticulation
    W[:, _C["jawOpen"]] = sm(jaw)
    W[:, _C["mouthFunnel"]] = sm(funnel)
    W[:, _C["mouthPucker"]] = sm(pucker)

    # --- smiles: slow episodes, slightly asymmetric, suppressed by rounding
    smile = np.zeros(n_frames)
    for e in _events(total, 4.0, r_expr, start=-1.0):
        smile = np.maximum(smile, r_expr.uniform(0.4, 1.0) * pulse(t, e, r_expr.uniform(0.8, 2.5), 0.35))
    asym = 0.25 * smooth_noise(n_frames, 2.0 * fps, r_expr)
    rounding = np.clip(W[:, _C["mouthFunnel"]] + W[:, _C["mouthPucker"]], 0, 1)
    base = (smile + 0.35 * sm(stretch)) * (1 - 0.8 * rounding)
    W[:, _C["mouthSmile_L"]] = base * (1 + asym)
    W[:, _C["mouthSmile_R"]] = base * (1 - asym)

    # --- brows: inner raises on emphasis, outer raises now and then, one side at a time sometimes
    brow_in = np.zeros(n_frames)
    for e in _events(total, 3.5, r_expr, start=-0.5):
        brow_in = np.maximum(brow_in, r_expr.uniform(0.3, 1.0) * pulse(t, e, r_expr.uniform(0.4, 1.5), 0.2))
    W[:, _C["browInnerUp"]] = brow_in
    for name in ("browOuterUp_L", "browOuterUp_R"):
        b = np.zeros(n_frames)
        for e in _events(total, 5.0, r_expr, start=-1.0):
            b = np.maximum(b, r_expr.uniform(0.3, 1.0) * pulse(t, e, r_expr.uniform(0.5, 1.8), 0.25))
        W[:, _C[name]] = np.maximum(b, 0.6 * brow_in)

    # --- blinks: every 2-5 s, 0.12-0.25 s long; one in seven is one eye only
    bl = np.zeros((n_frames, 2))
    for e in _events(total, 3.2, r_blink, start=-1.5):
        d = r_blink.uniform(0.12, 0.25)
        env = pulse(t, e, d, d * 0.45)
        which = r_blink.choice(3, p=[0.86, 0.07, 0.07])
        amp = r_blink.uniform(0.85, 1.0)
        if which in (0, 1):
            bl[:, 0] = np.maximum(bl[:, 0], amp * env)
        if which in (0, 2):
            bl[:, 1] = np.maximum(bl[:, 1], amp * env)
    W[:, _C["eyeBlink_L"]] = bl[:, 0]
    W[:, _C["eyeBlink_R"]] = bl[:, 1]
    W = np.clip(W, 0.0, 1.0)

    # --- gaze: fixations joined by saccades of ~3 frames
    times = np.concatenate([[-1.0], _events(total, 1.1, r_gaze)])
    targets = np.column_stack([r_gaze.uniform(-0.85, 0.85, len(times)), r_gaze.uniform(-0.6, 0.6, len(times))])
    targets[0] = r_gaze.uniform(-0.3, 0.3, 2)
    k = np.searchsorted(times, t, side="right") - 1
    gaze = targets[k]
    gaze = gaussian_filter1d(gaze, 0.7 * fps / 30.0, axis=0, mode="nearest")

    # --- head: slow drift plus occasional fast moves
    roll = 6.0 * smooth_noise(n_frames, 1.3 * fps, r_head)
    scale = 1.0 + 0.045 * smooth_noise(n_frames, 2.5 * fps, r_head)
    shift = np.column_stack([14.0 * smooth_noise(n_frames, 1.6 * fps, r_head),
                             7.0 * smooth_noise(n_frames, 1.4 * fps, r_head)])
    for e in _events(total, 3.0, r_head, start=0.5):
        d = r_head.uniform(0.15, 0.35)
        step = np.clip((t - e) / d, 0, 1)
        step = step * step * (3 - 2 * step)                  # smoothstep: a fast move that stays
        back = np.clip((t - e - r_head.uniform(0.8, 2.0)) / (2 * d), 0, 1)
        back = back * back * (3 - 2 * back)
        shape = step - back
        shift += shape[:, None] * r_head.uniform(-1, 1, 2) * [30.0, 14.0]
        roll += shape * r_head.uniform(-7, 7)
    roll = 15.0 * np.tanh(roll / 15.0)
    scale = 1.0 + 0.1 * np.tanh((scale - 1.0) / 0.1)

    # --- light: a slowly drifting direction; camera gain drifts a few percent
    az = 0.55 * np.sin(2 * np.pi * t / 17.0 + r_light.uniform(0, 2 * np.pi)) + 0.2 * smooth_noise(
        n_frames, 3 * fps, r_light)
    el = 0.55 + 0.12 * smooth_noise(n_frames, 4 * fps, r_light)
    light = np.column_stack([np.sin(az) * np.cos(el), -np.sin(el), np.cos(az) * np.cos(el)])
    exposure = 1.0 + 0.035 * smooth_noise(n_frames, 2.0 * fps, r_light)
    return Performance(W, gaze, roll, scale, shift, light, exposure, float(fps))
