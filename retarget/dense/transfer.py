"""Facial transfer by face-space deformation (section 6 of 002_dce09d5f5656b088.txt, eqs. 6-9).

Design notes and figures: docs/keypoints.md, "Notes on the code", ``retarget/dense/transfer.py``.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from keyshape.base.errors import InputError
from keyshape.retarget.dense.keypoints import check_sequence, face_rbf


#: the deformation's kernel width over the median spacing of the target key points (enough overlap that the
#: Gaussian interpolant does not sag between samples: docs/keypoints.md); the RBF systems' ridge; target vertices
#: deformed at a time (bounds the kernel matrix's memory)
SPREAD, SMOOTHING, CHUNK = 3.0, 1e-2, 8192


def transfer_sequence(frames: np.ndarray, source_keys: np.ndarray, target: np.ndarray, target_keys: np.ndarray,
                      *, n_samples: int = 6000, gain: float = 1.0, rng=None) -> np.ndarray:
    """Carry the motion of ``frames`` (n_frames, n_points, 3) onto ``target`` (n_vertices, 3).

    Parameters
    ----------
    frames : source sequence; frame 0 is the source's neutral face; points correspond over frames.
    source_keys : (n_keys,) vertex indices of the key points in the source (eq. 6).
    target : target neutral face ``T^0``.
    target_keys : (n_keys, 3) positions (or (n_keys,) vertex indices) of the same key points on the target.
    n_samples : number ``N_k`` of target key points sampled for eqs. (7)-(9).
    gain : ``alpha / N_k`` of eq. (8).
    rng : None, int or Generator (the random sampling of 6.2).

    The kernel width of eq. (9)'s deformation is :data:`SPREAD` x the median distance between neighbouring
    sampled key points (the morph of eq. (6) uses :func:`keyshape.retarget.dense.keypoints.face_rbf`'s default
    from the source keys); both RBF systems have the ridge :data:`SMOOTHING`; the target key points of eq. (6)
    are samples of eqs. (7)-(9) too; :data:`CHUNK` target vertices are deformed at a time.

    Returns
    -------
    (n_frames, n_vertices, 3) transferred target sequence ``T-hat^t``; frame 0 is ``target``.
    """
    frames = check_sequence(frames)
    target = np.asarray(target, np.float64)
    if target.ndim != 2 or target.shape[1] != 3:
        raise InputError(f"target: expected (n_vertices, 3), got {target.shape}")
    if not np.all(np.isfinite(target)):
        raise InputError("target: contains NaN or infinite values")
    sk = np.asarray(source_keys, np.intp)
    if sk.ndim != 1 or len(sk) == 0 or sk.min() < 0 or sk.max() >= frames.shape[1]:
        raise InputError(f"source key points must be a non-empty list of indices in 0..{frames.shape[1] - 1}")
    tk = np.asarray(target_keys)
    if tk.ndim == 1:
        if tk.min() < 0 or tk.max() >= len(target):
            raise InputError(f"target key points must lie in 0..{len(target) - 1}")
        tk = target[tk.astype(np.intp)]
    tk = tk.astype(np.float64)
    if tk.shape != (len(sk), 3):
        raise InputError(f"target_keys: expected ({len(sk)}, 3), got {tk.shape}")
    if n_samples < 1:
        raise InputError(f"n_samples must be at least 1, got {n_samples}")
    rng = np.random.default_rng(rng)
    # (6) FT^t = D(F^t -> T^0): the one space deformation K^0 -> K^T, applied to every frame
    morph = face_rbf(None, SMOOTHING).fit(frames[0, sk])
    ft0 = morph.deform(frames[0], tk)
    # (6.2) random target key points Kt_i, paired once on the neutrals with their nearest point of FT^0
    distinct = np.unique(target, axis=0, return_index=True)[1]  # meshes repeat positions at seams
    n_k = min(int(n_samples), len(distinct))
    kt = target[rng.choice(np.sort(distinct), size=n_k, replace=False)]
    kt = np.unique(np.concatenate([tk, kt]), axis=0)   # eq. 6's K^T are key points too: on the lips and eyes
    sigma = SPREAD * float(np.median(cKDTree(kt).query(kt, k=2)[0][:, 1]))
    src = cKDTree(ft0).query(kt)[1]
    # Kf^t_i: the same source point in every morphed frame (only the paired points need morphing)
    kf = np.stack([morph.deform(f[src], tk) for f in frames])       # (n_frames, n_k, 3)
    disp = kf - kf[0]
    norm = np.linalg.norm(disp, axis=2, keepdims=True)
    v = np.divide(disp, norm, out=np.zeros_like(disp), where=norm > 1e-12)   # (7)
    w = gain * norm                                                          # (8)
    moved = kt + w * v                                                       # (9)
    rbf = face_rbf(sigma, SMOOTHING).fit(kt)
    out = np.empty((len(frames), len(target), 3))
    for s in range(0, len(target), CHUNK):
        out[:, s:s + CHUNK] = rbf.deform(target[s:s + CHUNK], moved)
    out[0] = target  # frame 0 is the neutral: its displacements are zero, this removes round-off
    return out
