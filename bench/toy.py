"""A small synthetic performance for tests and benchmarks: low-rank non-negative expression model.

Design notes: docs/decompose.md, "Notes on the code", ``bench/toy.py``. The tests import it from here (tests/conftest.py
puts bench/ on the import path).
"""
from __future__ import annotations

import numpy as np

from keyshape.base.formats.tracks import Tracks
from keyshape.base.schemes import load_scheme


def mean_face() -> np.ndarray:
    """A plausible ``contours48`` neutral face (48, 2), about 100 px between the outer eye corners."""
    t5 = np.linspace(-1, 1, 5)
    pts = np.zeros((48, 2))
    for side, cx in ((0, -35.0), (1, 35.0)):
        pts[5 * side:5 * side + 5] = np.c_[cx + 22 * t5, -40 - 8 * (1 - t5 ** 2)]         # brows
        a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
        pts[10 + 8 * side:18 + 8 * side] = np.c_[cx - 15 * np.cos(a), -20 - 7 * np.sin(a)]  # eyes
        pts[26 + side] = (cx, -20)                                                          # pupils
    a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    pts[28:40] = np.c_[-32 * np.cos(a), 60 - 14 * np.sin(a)]                                # outer lip
    a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    pts[40:48] = np.c_[-24 * np.cos(a), 60 - 5 * np.sin(a)]                                 # inner lip
    return pts


def _smooth_noise(rng, n: int, width: float, size: tuple) -> np.ndarray:
    """Gaussian-filtered white noise along axis 0 (length n), unit std per column."""
    from scipy.ndimage import gaussian_filter1d

    x = gaussian_filter1d(rng.normal(size=(n, *size)), width, axis=0, mode="reflect")
    return x / x.std(axis=0, keepdims=True)


def toy_tracks(n_frames: int = 600, n_modes: int = 6, noise_px: float = 0.5, static_fraction: float = 0.3,
               fail_fraction: float = 0.0, rng=None, return_truth: bool = False):
    """A synthetic ``contours48`` performance as :class:`~keyshape.base.formats.tracks.Tracks`.

    Parameters
    ----------
    n_frames, n_modes : int
        Frames, and expression modes per region (mouth, eyes+brows, pupils get
        n_modes, n_modes, 2).
    noise_px : float
        Std of the Gaussian tracking noise added to every image coordinate.
    static_fraction : float
        Fraction of frames inside stretches where the expression holds still.
    fail_fraction : float
        Fraction of frames marked ``success=0`` (their points set to NaN).

    Returns
    -------
    Tracks (and, if ``return_truth``, a dict with the noiseless model-frame
    ``shapes`` and ``static`` (n_frames,) bool marking held frames).
    """
    rng = np.random.default_rng(rng)
    sch = load_scheme("contours48")
    base = mean_face()
    shapes = np.repeat(base[None], n_frames, axis=0)
    hold = np.zeros(n_frames, dtype=bool)
    n_static = int(static_fraction * n_frames)
    if n_static:
        length = max(10, n_frames // 20)
        for s in rng.choice(max(n_frames - length, 1), size=max(1, n_static // length), replace=False):
            hold[s:s + length] = True
    for region, r in (("mouth", n_modes), ("brows+eyes", n_modes), ("pupils", 2)):
        idx = sch.region(region)
        ext = np.ptp(base[idx], axis=0).max()
        # smooth modes: random low-order polynomial fields of the points' positions
        p = (base[idx] - base[idx].mean(0)) / ext
        feats = np.column_stack([np.ones(len(idx)), p, p ** 2, p[:, :1] * p[:, 1:]])
        modes = np.einsum("pf,mfd->mpd", feats, rng.normal(size=(r, feats.shape[1], 2))) * 0.15 * ext
        modes[:, np.isin(idx, sch.rigid)] = 0.0          # the eye corners stay on the skull, as in a face
        if region == "pupils":
            modes = np.stack([np.tile([4.0, 0], (2, 1)), np.tile([0, 3.0], (2, 1))])
            act = _smooth_noise(rng, n_frames, 6, (r,))
        else:
            act = np.maximum(_smooth_noise(rng, n_frames, 4, (r,)) - 0.3, 0.0) * (rng.random(r) + 0.5)
        # hold each static stretch at its first frame's activations
        starts = np.flatnonzero(hold & ~np.r_[False, hold[:-1]])
        for s in starts:
            e = s + np.argmin(hold[s:]) if not hold[s:].all() else n_frames
            act[s:e] = act[s]
        shapes[:, idx] += np.einsum("tm,mpd->tpd", act, modes)
    ang = 0.1 * _smooth_noise(rng, n_frames, 20, ())
    scale = 1.0 + 0.05 * _smooth_noise(rng, n_frames, 20, ())
    shift = np.array([160.0, 140.0]) + 8 * _smooth_noise(rng, n_frames, 20, (2,))
    c, s = np.cos(ang) * scale, np.sin(ang) * scale
    pose = np.stack([np.stack([c, -s, shift[:, 0]], 1), np.stack([s, c, shift[:, 1]], 1)], 1)
    img = np.einsum("tij,tpj->tpi", pose[:, :, :2], shapes) + pose[:, None, :, 2]
    img += rng.normal(scale=noise_px, size=img.shape)
    success = np.ones(n_frames, dtype=bool)
    if fail_fraction > 0:
        success[rng.choice(n_frames, int(fail_fraction * n_frames), replace=False)] = False
        img[~success] = np.nan
    tracks = Tracks(np.arange(n_frames), np.arange(n_frames) / 25.0, success.astype(float), success, img, pose)
    if return_truth:
        return tracks, {"shapes": shapes, "static": hold}
    return tracks
