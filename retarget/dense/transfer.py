"""Facial transfer by face-space deformation (section 6 of 002_dce09d5f5656b088.txt, eqs. 6-9).

Steps: (6) deform every source frame ``F^t`` into the target's space,
``FT^t = D(F^t -> T^0)``, with the key points (source key positions of frame
t sent to the target's key points); (6.2) sample target key points
``Kt_i`` at random on ``T^0`` and find their nearest points ``Kf^t_i`` in
``FT^t``; (7) ``V^t_i = (Kf^t_i - Kt_i) / ||Kf^t_i - Kt_i||``;
(8) ``W^t_i = alpha / N_k ||Kf^0_i - Kf^t_i||``; (9) deform ``T^0`` with the
key pairs ``Kt_i -> Kt_i + W^t_i V^t_i``.

Reading of eq. (6): if ``D^t`` sent each frame's *tracked* key points
``K^t`` to the target's, ``FT^t`` would equal ``T^0`` at every key point
and the motion would be erased; the paper says the remaining difference
``FT^t - T^0`` *is* the motion, so ``D^t`` is the one space deformation
that sends the source's rest key points ``K^0`` onto the target's, applied
to each frame ``F^t``.

Derivation: since ``FT^0 ~ T^0`` (frame 0 is the neutral), ``Kf^0_i ~ Kt_i``
and ``W V ~ (alpha / N_k) (Kf^t_i - Kt_i)`` in magnitude: the target key
points move by the source's motion seen in the target's space, scaled by
``alpha / N_k``. We therefore expose ``gain = alpha / N_k`` (default 1: the
motion is carried over at its own size); ``gain = 0`` leaves the target
still. Where ``Kf^t_i = Kt_i`` the direction of eq. (7) is undefined and the
displacement is zero.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.errors import InputError
from retarget.dense.keypoints import check_sequence
from retarget.dense.rbf_face import FaceSpaceRBF


def transfer_sequence(frames: np.ndarray, source_keys: np.ndarray, target: np.ndarray, target_keys: np.ndarray,
                      *, n_samples: int = 300, gain: float = 1.0, sigma: float | None = None,
                      smoothing: float = 1e-2, rng=None) -> np.ndarray:
    """Carry the motion of ``frames`` (n_frames, n_points, 3) onto ``target`` (n_vertices, 3).

    Parameters
    ----------
    frames : source sequence; frame 0 is the source's neutral face.
    source_keys : (n_keys,) vertex indices of the key points in the source.
    target : target neutral face ``T^0``.
    target_keys : (n_keys, 3) positions (or (n_keys,) vertex indices) of the same key points on the target.
    n_samples : number ``N_k`` of target key points sampled for eqs. (7)-(9).
    gain : ``alpha / N_k`` of eq. (8).
    rng : None, int or Generator (the random sampling of 6.2).

    Returns
    -------
    (n_frames, n_vertices, 3) transferred target sequence ``T-hat^t``; frame 0 is ``target``.
    """
    frames = check_sequence(frames)
    target = np.asarray(target, np.float64)
    if target.ndim != 2 or target.shape[1] != 3:
        raise InputError(f"target: expected (n_vertices, 3), got {target.shape}")
    sk = np.asarray(source_keys, np.intp)
    if sk.min() < 0 or sk.max() >= frames.shape[1]:
        raise InputError(f"source key points must lie in 0..{frames.shape[1] - 1}")
    tk = np.asarray(target_keys)
    if tk.ndim == 1:
        if tk.min() < 0 or tk.max() >= len(target):
            raise InputError(f"target key points must lie in 0..{len(target) - 1}")
        tk = target[tk.astype(np.intp)]
    tk = tk.astype(np.float64)
    if tk.shape != (len(sk), 3):
        raise InputError(f"target_keys: expected ({len(sk)}, 3), got {tk.shape}")
    rng = np.random.default_rng(rng)
    n_frames = len(frames)
    # (6) FT^t = D(F^t -> T^0): the space deformation sending the source's rest key points to the
    # target's, applied to every frame (so the motion relative to F^0 survives into T^0's space)
    morph = FaceSpaceRBF(frames[0, sk], sigma=sigma, smoothing=smoothing)
    ft = np.stack([morph.deform(f, tk) for f in frames])
    # (6.2) random target key points and their nearest points in each FT^t
    distinct = np.unique(target, axis=0, return_index=True)[1]  # meshes repeat positions at seams
    n_k = min(n_samples, len(distinct))
    kt_idx = rng.choice(np.sort(distinct), size=n_k, replace=False)
    kt = target[kt_idx]
    kf = np.stack([f[cKDTree(f).query(kt)[1]] for f in ft])  # (n_frames, n_k, 3)
    diff = kf - kt
    norm = np.linalg.norm(diff, axis=2, keepdims=True)
    v = np.divide(diff, norm, out=np.zeros_like(diff), where=norm > 1e-12)   # (7)
    w = gain * np.linalg.norm(kf[0] - kf, axis=2, keepdims=True)               # (8)
    moved = kt + w * v                                                        # (9)
    rbf = FaceSpaceRBF(kt, sigma=sigma, smoothing=smoothing)
    return rbf.deform(target, moved)
