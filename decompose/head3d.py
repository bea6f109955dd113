"""The head's 3D pose from a 2D track, and the shapes in the head's frame (frontalised).

:class:`HeadPose3D`: the scheme's points on ICT-FaceKit's generic neutral adapted to the actor; per frame a pose
minimising the weighted reprojection error under a pinhole camera (Eq. 1, Levenberg-Marquardt, all frames at once);
each observed point taken back along its ray to its face point's frontal plane (Eq. 2), each pupil to its eyeball
(Eq. 3); angles ``R = Rz(roll) Ry(yaw) Rx(pitch)`` in ARKit's head axes (:func:`euler_angles`).
The equations, the axes and the design: docs/decompose.md, "Notes on the code", ``decompose/head3d.py``.
"""
from __future__ import annotations

import hashlib
from typing import Sequence

import numpy as np
from scipy.ndimage import gaussian_filter1d

from keyshape.base.errors import InputError, NotFittedError

#: camera axes (x right, y down, z away from the camera) from head axes (x left of the actor, y up, z forward)
FLIP = np.diag([1.0, -1.0, -1.0])
_DIAG3, _DIAG6 = np.arange(3), np.arange(6)
#: flat positions in a 3x3 matrix of [v]_x's entries -v_z, v_y, -v_x (upper) and v_z, -v_y, v_x (lower)
_HAT9, _HAT9_FROM, _HAT9_SIGN = np.array([1, 2, 5, 3, 6, 7]), np.array([2, 1, 0, 2, 1, 0]), \
    np.array([-1.0, 1.0, -1.0, 1.0, -1.0, 1.0])
_SKEW_PLUS, _SKEW_MINUS = np.array([7, 2, 3]), np.array([5, 6, 1])


def _hat(v: np.ndarray) -> np.ndarray:
    """(..., 3) vectors -> (..., 3, 3) cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def rodrigues(v: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3): ``exp([v]_x)``."""
    v = np.asarray(v, np.float64)
    th = np.linalg.norm(v, axis=-1)[..., None, None]
    K = _hat(v)
    small = th < 1e-12
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0, np.sin(ths) / ths)
    b = np.where(small, 0.5, (1 - np.cos(ths)) / ths ** 2)
    return np.eye(3) + a * K + b * (K @ K)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3) (angles below pi)."""
    R = np.asarray(R, np.float64)
    return _rotvec(R.reshape(-1, 3, 3)).reshape(R.shape[:-1])


def euler_angles(R: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) in radians (..., 3) of head rotations (..., 3, 3) in head axes.

    ``R = Rz(roll) Ry(yaw) Rx(pitch)``: ``yaw = asin(-R_20)``, ``pitch = atan2(R_21, R_22)``,
    ``roll = atan2(R_10, R_00)`` (MediaPipe's face-geometry matrix read the same way).
    """
    R = np.asarray(R, np.float64)
    yaw = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 2, 1], R[..., 2, 2]))
    pitch = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    roll = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([yaw, pitch, roll], -1)


def from_euler(yaw, pitch, roll) -> np.ndarray:
    """Head rotations (..., 3, 3) from (yaw, pitch, roll) radians: ``Rz(roll) Ry(yaw) Rx(pitch)``."""
    y, p, r = (np.asarray(a, np.float64) for a in (yaw, pitch, roll))
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    o, z = np.ones_like(y + p + r), np.zeros_like(y + p + r)
    Rz = np.stack([np.stack([cr, -sr, z], -1), np.stack([sr, cr, z], -1), np.stack([z, z, o], -1)], -2)
    Ry = np.stack([np.stack([cy, z, sy], -1), np.stack([z, o, z], -1), np.stack([-sy, z, cy], -1)], -2)
    Rx = np.stack([np.stack([o, z, z], -1), np.stack([z, cp, -sp], -1), np.stack([z, sp, cp], -1)], -2)
    return Rz @ Ry @ Rx


def project(X: np.ndarray, R: np.ndarray, t: np.ndarray, focal: float, centre: np.ndarray) -> np.ndarray:
    """Pinhole projection (Eq. 1) of face points ``X`` (n, 3) (camera axes) posed by ``R`` (T, 3, 3),
    ``t`` (T, 3): (T, n, 2) pixels."""
    P = np.einsum("tij,nj->tni", R, X) + t[:, None]
    return focal * P[..., :2] / P[..., 2:3] + centre


def _rodrigues_left(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``exp([v]_x) @ R`` for (T, 3) rotation vectors and (T, 3, 3) rotations (:func:`rodrigues` in
    fewer array operations: ``I + a [v]_x + b (v v^T - |v|^2 I)``)."""
    th2 = np.einsum("ti,ti->t", v, v)
    th = np.maximum(np.sqrt(th2), 1e-12)               # below: a = 1 and b v v^T = 0 to the last bit
    a = np.sin(th) / th
    b = (1 - np.cos(th)) / (th * th)
    E = (b[:, None] * v)[:, :, None] * v[:, None, :]
    E.reshape(-1, 9)[:, _HAT9] += (a[:, None] * v)[:, _HAT9_FROM] * _HAT9_SIGN
    E.reshape(-1, 9)[:, ::4] += (1 - b * th2)[:, None]
    return E @ R


def _rotvec(R: np.ndarray) -> np.ndarray:
    """:func:`rotation_vector` of (T, 3, 3) rotations."""
    Rf = R.reshape(-1, 9)
    th = np.arccos(np.minimum(np.maximum((Rf[:, ::4].sum(-1) - 1) / 2, -1.0), 1.0))
    k = np.where(th < 1e-9, 0.5, th / (2 * np.sin(np.maximum(th, 1e-9))))
    return (Rf[:, _SKEW_PLUS] - Rf[:, _SKEW_MINUS]) * k[:, None]      # (R_21 - R_12, R_02 - R_20, R_10 - R_01)


def _residuals(Xt: np.ndarray, qt: np.ndarray, focal: float, R: np.ndarray, t: np.ndarray):
    """Eq. 1's residuals (T, 2, n), the posed points' ``R X`` (T, 3, n), ``(x, y) / z`` (T, 2, n) and
    ``1/z`` (T, n) for face points ``Xt`` (3, n) and centred pixels ``qt = p - c`` (T, 2, n)."""
    RX = R @ Xt
    P = RX + t[:, :, None]
    iz = 1.0 / P[:, 2]
    uv = P[:, :2] * iz[:, None]
    return focal * uv - qt, RX, uv, iz


def solve_pose(X: np.ndarray, p: np.ndarray, w: np.ndarray, focal: float, centre: np.ndarray,
               R0: np.ndarray, t0: np.ndarray, n_iter: int = 30, prior: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on Eq. 1 for every frame at once.

    Each frame stops on its own (a step below 1e-7 in every coordinate), and an iteration computes
    only the frames still moving. The Jacobian of a point's residual is written out: with ``a = R X``,
    ``P = a + t``, ``u = P_x / P_z``, ``v = P_y / P_z`` and the increment ``(d, dt)`` of
    ``R <- exp([d]_x) R``, ``t <- t + dt``,

    ``d r_x = f / P_z (-u a_y, a_z + u a_x, -a_y, 1, 0, -u)``,
    ``d r_y = f / P_z (-a_z - v a_y, v a_x, a_x, 0, 1, -v)``,

    and the ``f / P_z`` folded into the weights of the 6x6 normal equations. Points of weight 0 in every
    frame are left out (they add nothing to Eq. 1).

    Parameters
    ----------
    X : (n, 3) face points, camera axes
    p : (T, n, 2) observed pixels (no NaN: give those points weight 0 and any value)
    w : (T, n) or (n,) weights
    focal, centre : pinhole focal length (pixels) and principal point (2,)
    R0, t0 : (T, 3, 3), (T, 3) starting poses
    prior : ``lambda`` of a Gaussian prior on the rotation (facing the camera), ``+ lambda |omega|^2``
        added to Eq. 1 (``omega`` the rotation vector; pixels^2 per radian^2)

    Returns
    -------
    R : (T, 3, 3), t : (T, 3) camera-axes pose of each frame (``P = R X + t``)
    """
    R = np.array(R0, np.float64)
    t = np.array(t0, np.float64)
    T = len(p)
    w = np.broadcast_to(np.asarray(w, np.float64), p.shape[:2])
    used = (w > 0).any(0)
    w = np.ascontiguousarray(w[:, used])
    Xt = np.ascontiguousarray(np.asarray(X, np.float64)[used].T)
    qt = np.ascontiguousarray((np.asarray(p, np.float64)[:, used] - centre).transpose(0, 2, 1))
    n = Xt.shape[1]

    def cost(R, t, qt, w):
        r = _residuals(Xt, qt, focal, R, t)[0]
        e = (w * (r * r).sum(1)).sum(-1)
        if not prior:
            return e, None
        om = _rotvec(R)
        return e + prior * np.einsum("ti,ti->t", om, om), om

    E, om = cost(R, t, qt, w)
    lam = np.full(T, 1e-3)
    act = np.arange(T)
    J = np.zeros((T, 6, 2, n))                 # d r / d (d, dt) without its f / P_z
    J[:, 3, 0] = 1.0
    J[:, 4, 1] = 1.0
    for _ in range(n_iter):
        m = len(act)
        Ra, ta, qa, wa = (R, t, qt, w) if m == T else (R[act], t[act], qt[act], w[act])
        r, RX, uv, iz = _residuals(Xt, qa, focal, Ra, ta)
        ax, ay, az = RX[:, 0], RX[:, 1], RX[:, 2]
        Jm = J[:m]
        Jm[:, 0] = uv * -ay[:, None]
        Jm[:, 0, 1] -= az
        Jm[:, 1] = uv * ax[:, None]
        Jm[:, 1, 0] += az
        Jm[:, 2, 0] = -ay
        Jm[:, 2, 1] = ax
        Jm[:, 5] = -uv
        fz = focal * iz
        wf = wa * fz
        wf2 = wf * fz
        Jm = Jm.reshape(m, 6, 2 * n)
        H = (Jm * np.concatenate([wf2, wf2], -1)[:, None]) @ Jm.transpose(0, 2, 1)
        g = Jm @ (r * wf[:, None]).reshape(m, 2 * n, 1)
        if prior:                                  # d omega / d (left increment) ~ I near the camera-facing pose
            H[:, _DIAG3, _DIAG3] += prior
            g[:, :3, 0] += prior * om[act]
        la = lam[act]
        H[:, _DIAG6, _DIAG6] += la[:, None] * (H[:, _DIAG6, _DIAG6] + 1e-9)
        step = -np.linalg.solve(H, g)[..., 0]
        Rn = _rodrigues_left(step[:, :3], Ra)
        tn = ta + step[:, 3:]
        En, omn = cost(Rn, tn, qa, wa)
        better = En <= E[act]
        idx = act[better]
        R[idx], t[idx], E[idx] = Rn[better], tn[better], En[better]
        if prior:
            om[idx] = omn[better]
        lam[act] = np.where(better, la * 0.3, la * 10.0)
        act = act[np.abs(step).max(-1) >= 1e-7]
        if not len(act):
            break
    return R, t


def frontalise(X: np.ndarray, p: np.ndarray, R: np.ndarray, t: np.ndarray, focal: float,
               centre: np.ndarray, eyeballs: Sequence[int] = (), eye_radius: float = 1.2) -> np.ndarray:
    """Observed pixels ``p`` (T, n, 2) in the head's frame (Eq. 2): (T, n, 3) camera axes at the
    head's rest orientation; the face points ``X`` (n, 3) give each point's frontal plane.

    The points ``eyeballs`` (pupils) are taken back along their rays to their eyeball instead (Eq. 3): a sphere of
    radius ``eye_radius`` (cm) centred ``eye_radius`` behind the point's rest place ``X_i``, the ray's first
    crossing (its nearest approach where the ray misses it).
    """
    q = np.concatenate([(p - centre) / focal, np.ones(p.shape[:2] + (1,))], -1)   # rays
    n = R[:, :, 2]                                                                  # R e_z
    P = np.einsum("tij,nj->tni", R, X) + t[:, None]
    lam = np.einsum("ti,tni->tn", n, P) / np.einsum("ti,tni->tn", n, q)
    eb = list(eyeballs)
    if eb:
        # Eq. 3: |lam q - C|^2 = r^2 with C = R (X_i + r e_z) + t (camera z points away from the face)
        C = P[:, eb] + eye_radius * n[:, None]
        qe = q[:, eb]
        a = np.einsum("tni,tni->tn", qe, qe)
        b = np.einsum("tni,tni->tn", qe, C)
        disc = np.maximum(b * b - a * (np.einsum("tni,tni->tn", C, C) - eye_radius ** 2), 0.0)
        lam[:, eb] = (b - np.sqrt(disc)) / a
    Y = lam[..., None] * q
    return np.einsum("tji,tnj->tni", R, Y - t[:, None])


def _frontalise_ok(X, p, R, t, ok, focal, centre, eyeballs=(), eye_radius=1.2) -> np.ndarray:
    """:func:`frontalise` with the frames not ``ok`` given harmless values (their rows are not meaningful)."""
    return frontalise(X, np.where(ok[:, None, None], p, 0.0), np.where(ok[:, None, None], R, np.eye(3)),
                      np.where(ok[:, None], t, 1.0), focal, centre, eyeballs, eye_radius)


def mirror_pairs(template: np.ndarray) -> np.ndarray:
    """Index of each point's left-right mirror image on a face (n, 3) symmetric about x = 0."""
    m = template * np.array([-1.0, 1.0, 1.0])
    d = np.linalg.norm(template[:, None] - m[None], axis=-1)
    return d.argmin(1)


class HeadPose3D:
    """A track's head pose in 3D and its shapes in the head's frame (Eqs. 1-2 of docs/decompose.md).

    Parameters
    ----------
    template : (n_points, 3) the scheme's points on a generic face, head axes (x the actor's
        left, y up, z out of the face), cm (:func:`keyshape.base.schemes.load_head_template`)
    weights : (n_points,) each point's weight ``w_i`` in Eq. 1 (the template's: 1 on the points
        rigid with the skull, less on those expression moves, 0 on pupils and the lower mouth)
    rigid : indices of the points rigid with the skull (``Scheme.rigid``): the output frame's anchor
    distance : assumed camera distance of the face (cm) for the focal length guess
    smooth : Gaussian sigma (frames) of the temporal smoothing of the pose; 0: none
    adapt : adapt the face's x, y to the actor's rest frame (symmetrised)
    focal, centre : the camera's focal length and principal point (pixels) when known (default: guessed)
    anchor : after Eq. 2, map each frame's rigid points onto the zero frame's by a 2D similarity (the
        3D pose takes the turn out of the plane, the rigid points fix what is left in the plane)
    robust, robust_rounds : per frame, ``robust_rounds`` reweightings of Eq. 1 with Cauchy weights
        ``w_i / (1 + (r_i / c)^2)`` of each point's residual ``r_i`` (first at the 2D similarity's pose),
        ``c`` = ``robust`` x the rigid points' spread in the image: a point the expression moves far is
        trusted less in that frame (0: none)
    spread : degrees, the spread of a Gaussian prior on the head's rotation away from facing the camera
        (``solve_pose``'s ``prior``; 0: none)
    eyeballs, eye_radius : the points (pupils) that turn on an eyeball of ``eye_radius`` cm behind their rest
        place, taken back to it rather than to their frontal plane (:func:`frontalise`, Eq. 3)

    Attributes
    ----------
    template_ : (n_points, 3) the actor's face, camera axes (x right, y down, z away), cm
    focal_ : float, pixels
    centre_ : (2,) principal point, pixels
    zero_ : (3, 3) camera-axes rotation of the zero frame
    camera_pose_ : ``(R, t)`` what :meth:`camera_pose` gives for the points given to :meth:`fit` (its solve,
        to pass on as ``pose`` to :meth:`head_pose` and :meth:`transform` of those points; not in KEYS.json)
    zero_frame_ : int, row of the zero frame in the shapes given to :meth:`fit`
    frame_ : (3,) ``(s, tx, ty)``: head-frame shape ``= s * H_xy + (tx, ty)`` (rest-frame pixels)
    reference_ : (n_rigid, 2) the zero frame's rigid points in the head frame (``anchor``)
    weights_ : (n_points,) point weights of Eq. 1
    """

    def __init__(self, template: np.ndarray, weights: Sequence[float], rigid: Sequence[int], distance: float = 60.0,
                 smooth: float = 1.0, adapt: bool = True, focal: float | None = None,
                 centre: Sequence[float] | None = None, anchor: bool = False, spread: float = 20.0,
                 robust: float = 0.1, robust_rounds: int = 2, eyeballs: Sequence[int] = (),
                 eye_radius: float = 1.2):
        self.eyeballs = tuple(int(i) for i in eyeballs)
        self.eye_radius = float(eye_radius)
        self.robust = float(robust)
        self.robust_rounds = int(robust_rounds)
        self.anchor = bool(anchor)
        self.spread = float(spread)
        self.focal = None if focal is None else float(focal)
        self.centre = None if centre is None else tuple(float(c) for c in centre)
        self.template = np.asarray(template, np.float64)
        self.weights = tuple(float(x) for x in weights)
        self.rigid = tuple(int(i) for i in rigid)
        self.distance = float(distance)
        self.smooth = float(smooth)
        self.adapt = bool(adapt)

    # ------------------------------------------------------------------ checks
    def _check(self, points) -> np.ndarray:
        arr = np.asarray(points, np.float64)
        n = len(self.template)
        if self.template.ndim != 2 or self.template.shape[1] != 3 or not np.isfinite(self.template).all():
            raise InputError(f"a 3D head template must be (n_points, 3) finite, got {self.template.shape}")
        if arr.ndim != 3 or arr.shape[1:] != (n, 2):
            raise InputError(f"points of shape {arr.shape} do not match the 3D head template's {n} points")
        if len(self.rigid) < 2 or min(self.rigid) < 0 or max(self.rigid) >= n:
            raise InputError(f"the 3D head pose needs two or more rigid points in 0..{n - 1}, got {list(self.rigid)}")
        w = np.asarray(self.weights)
        if len(w) != n or not np.isfinite(w).all() or (w < 0).any() or (w[list(self.rigid)] <= 0).any():
            raise InputError(f"the 3D head pose needs {n} finite weights >= 0, positive on the rigid points")
        if self.smooth < 0 or self.distance <= 0:
            raise InputError(f"bad 3D head settings: smooth {self.smooth} (>= 0), distance {self.distance} (> 0)")
        return arr

    def _initial(self, X: np.ndarray, p: np.ndarray, w: np.ndarray, focal: float, centre: np.ndarray):
        """Starting poses: the weighted 2D similarity of the face's x, y onto each frame's points (its
        in-plane angle, and the depth its scale gives), facing the camera."""
        from keyshape.base.geometry import rigid_fit
        T = len(p)
        rot, trans, sc = rigid_fit(X[:, :2], p, weights=np.broadcast_to(w, p.shape[:2]), scale=True)
        bad = ~np.isfinite(rot).all(axis=(1, 2)) | ~(sc > 0)
        rot[bad], trans[bad], sc[bad] = np.eye(2), p[bad].mean(1), 1.0
        R = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
        R[:, :2, :2] = rot
        z = focal / sc
        t = np.concatenate([(trans - centre) * (z / focal)[:, None], z[:, None]], -1)
        return R, t

    def _image_spread(self, X: np.ndarray, focal: float) -> float:
        """The rigid points' RMS spread in the image (pixels), the face ``distance`` away."""
        rig = list(self.rigid)
        return np.sqrt(((X[rig, :2] - X[rig, :2].mean(0)) ** 2).sum(-1).mean()) * focal / self.distance

    def _prior(self, X: np.ndarray, focal: float) -> float:
        """``lambda`` of Eq. 1's rotation prior: ``(sigma_p / sigma_R)^2`` with ``sigma_R`` = ``spread``
        degrees and ``sigma_p`` 3% of the rigid points' spread in the image."""
        if self.spread <= 0:
            return 0.0
        return float((0.03 * self._image_spread(X, focal) / np.radians(self.spread)) ** 2)

    def _poses(self, X, p, ok, w, focal, centre):
        """Raw (unsmoothed) camera-axes poses of the frames ``ok``; others NaN."""
        T = len(p)
        R = np.full((T, 3, 3), np.nan)
        t = np.full((T, 3), np.nan)
        if ok.any():
            R0, t0 = self._initial(X, p[ok], w, focal, centre)
            lam = self._prior(X, focal)
            c = self._robust_scale(X, focal)
            Ro, to, wr = R0, t0, w
            for k in range(self.robust_rounds + 1 if c > 0 else 1):
                if c > 0:
                    # Cauchy weights from the last pose (first: the 2D similarity, facing the camera): a point
                    # that expression moved far from the face is trusted less in this frame
                    res = np.linalg.norm(project(X, Ro, to, focal, centre) - p[ok], axis=-1)
                    wr = w / (1 + (res / c) ** 2)
                Ro, to = solve_pose(X, p[ok], wr, focal, centre, Ro, to, n_iter=30 if k == 0 else 15, prior=lam)
            R[ok], t[ok] = Ro, to
        return R, t

    def _robust_scale(self, X: np.ndarray, focal: float) -> float:
        return self.robust * self._image_spread(X, focal)

    # ------------------------------------------------------------------ fit
    def fit(self, points: np.ndarray) -> "HeadPose3D":
        """Learn the actor's face, the camera guess, the point weights and the zero frame from
        (n_frames, n_points, 2) image points (NaN rows: failed frames)."""
        p = self._check(points)
        ok = np.isfinite(p).all(axis=(1, 2))
        if not ok.any():
            raise InputError("no successful frame to take the head's pose from")
        rig = list(self.rigid)
        X = self.template @ FLIP.T                       # camera axes at rest
        w = np.asarray(self.weights, np.float64)
        pairs = mirror_pairs(self.template)
        centre = np.nanmean(p[ok][:, rig].reshape(-1, 2), axis=0) if self.centre is None \
            else np.asarray(self.centre, np.float64)
        # rest frame for the adaptation: the frame nearest the take's median shape after a similarity
        rest = self._relaxed(p, ok, None)
        io = np.linalg.norm(X[rig].max(0)[:2] - X[rig].min(0)[:2])
        io_img = np.linalg.norm(p[rest, rig].max(0) - p[rest, rig].min(0))
        focal = self.distance * io_img / io if self.focal is None else self.focal
        for _ in range(2 if self.adapt else 0):
            R, t = self._poses(X, p[rest:rest + 1], np.ones(1, bool), w, focal, centre)
            H = frontalise(X, p[rest:rest + 1], R, t, focal, centre)[0]
            Xn = X.copy()
            Xn[:, :2] = H[:, :2]
            sym = Xn * np.array([-1.0, 1.0, 1.0])
            X = (Xn + sym[pairs]) / 2
            X[:, 2] = (self.template @ FLIP.T)[:, 2]
        self.template_, self.focal_, self.centre_, self.weights_ = X, float(focal), centre, w
        R, t = self._poses(X, p, ok, w, focal, centre)
        R, t = self._smooth(R, t, ok)
        self.camera_pose_ = (R, t)
        self._pose_memo = (self._pose_key(p), (R.copy(), t.copy()))  # camera_pose of these points: this solve
        H = _frontalise_ok(X, p, R, t, ok, focal, centre)
        H[~ok] = np.nan
        if self.eyeballs:
            # each eyeball behind where its pupil sits looking straight ahead: the take's median pupil (the
            # gaze's zero, keyshape.decompose.gaze), not the rest frame's, whose eyes may look elsewhere
            eb = list(self.eyeballs)
            X = X.copy()
            X[eb, :2] = np.median(H[ok][:, eb, :2], axis=0)
            self.template_ = X
        self.zero_frame_ = self._relaxed(H[..., :2], ok, R)
        self.zero_ = R[self.zero_frame_]
        # output frame: head-frame x, y scaled and shifted onto the rest frame's rigid points (pixels)
        hr = H[self.zero_frame_, rig, :2]
        pr = p[self.zero_frame_, rig]
        s = np.sqrt(((pr - pr.mean(0)) ** 2).sum() / max(((hr - hr.mean(0)) ** 2).sum(), 1e-12))
        self.frame_ = np.array([s, *(pr.mean(0) - s * hr.mean(0))])
        self.reference_ = s * hr + self.frame_[1:]
        return self

    def _relaxed(self, shapes: np.ndarray, ok: np.ndarray, R: np.ndarray | None) -> int:
        """Row of the most front-facing (``R`` given) of the 20% frames nearest the median shape
        (each frame's shape brought onto the median by a similarity); the nearest one without ``R``."""
        rows = np.flatnonzero(ok)
        S = shapes[rows]
        S = S - S.mean(1, keepdims=True)
        S = S / np.sqrt((S ** 2).sum((1, 2)))[:, None, None]
        med = np.median(S, axis=0)
        # optimal 2D rotation of each frame onto the median (closed form)
        a = np.einsum("tni,ni->t", S, med)
        b = (S[..., 0] * med[:, 1] - S[..., 1] * med[:, 0]).sum(1)
        d = 2 - 2 * np.hypot(a, b)
        if R is None:
            return int(rows[np.argmin(d)])
        near = d <= np.quantile(d, 0.2)
        ang = np.linalg.norm(rotation_vector(R[rows]), axis=-1)
        return int(rows[near][np.argmin(ang[near])])

    def _smooth(self, R: np.ndarray, t: np.ndarray, ok: np.ndarray):
        if self.smooth <= 0 or ok.sum() < 2:
            return R, t
        rows = np.flatnonzero(ok)
        v = rotation_vector(R[rows])                  # about the camera-facing pose: the same in any call
        v = gaussian_filter1d(v, self.smooth, axis=0, mode="nearest")
        tt = gaussian_filter1d(t[rows], self.smooth, axis=0, mode="nearest")
        R, t = R.copy(), t.copy()
        R[rows] = rodrigues(v)
        t[rows] = tt
        return R, t

    # ------------------------------------------------------------------ transform
    def _fitted(self):
        if not hasattr(self, "template_"):
            raise NotFittedError("this HeadPose3D is not fitted yet: call fit(points) first")

    def _pose_key(self, p: np.ndarray) -> tuple:
        """What a pose solve of ``p`` depends on besides the learned face: the points and the solve's settings."""
        digest = hashlib.blake2b(np.ascontiguousarray(p).tobytes(), digest_size=16).digest()
        return p.shape, digest, self.smooth, self.robust, self.robust_rounds, self.spread

    def camera_pose(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(T, 3, 3) rotations and (T, 3) translations (cm), camera axes, smoothed; NaN where a frame is NaN.

        The last solve is kept (the points' digest and the solve's settings its key; :meth:`fit` keeps its own):
        :meth:`head_pose`, :meth:`transform` and :meth:`image_from_head` of the same points share one solve,
        as a live frame's head and gaze do."""
        self._fitted()
        p = self._check(points)
        key = self._pose_key(p)
        memo = getattr(self, "_pose_memo", None)
        if memo is None or memo[0] != key:
            ok = np.isfinite(p).all(axis=(1, 2))
            R, t = self._poses(self.template_, p, ok, self.weights_, self.focal_, self.centre_)
            memo = self._pose_memo = (key, self._smooth(R, t, ok))
        R, t = memo[1]
        return R.copy(), t.copy()

    def head_pose(self, points: np.ndarray, pose: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
        """The head's motion from the zero frame, per frame (``pose``: :meth:`camera_pose` of ``points``
        when already solved, e.g. ``camera_pose_`` after :meth:`fit` on them; default: solved here).

        Returns
        -------
        dict with ``rotation`` (T, 3, 3) head axes (``R_head = F R_t R_0^T F``, ``F`` the axis flip),
        ``angles`` (T, 3) yaw, pitch, roll in radians (:func:`euler_angles`), ``translation`` (T, 3)
        cm in head axes from the zero frame's position, and ``depth`` (T,) the face's distance in cm
        (all NaN in failed frames)
        """
        R, t = self.camera_pose(points) if pose is None else pose
        Rh = FLIP @ np.einsum("tij,kj->tik", R, self.zero_) @ FLIP
        zero_t = t[self.zero_frame_] if self.zero_frame_ < len(t) and np.isfinite(t[self.zero_frame_]).all() \
            else np.nanmedian(t, axis=0)
        return {"rotation": Rh, "angles": euler_angles(Rh), "translation": (t - zero_t) @ FLIP.T,
                "depth": t[:, 2]}

    def transform(self, points: np.ndarray, pose: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(T, n_points, 2) head-frame shapes (Eq. 2, in the rest frame's pixels; NaN rows stay NaN);
        ``pose``: :meth:`camera_pose` of ``points`` when already solved (as in :meth:`head_pose`)."""
        self._fitted()
        p = self._check(points)
        ok = np.isfinite(p).all(axis=(1, 2))
        R, t = self.camera_pose(p) if pose is None else pose
        H = _frontalise_ok(self.template_, p, R, t, ok, self.focal_, self.centre_, self.eyeballs,
                           self.eye_radius)[..., :2]
        out = self.frame_[0] * H + self.frame_[1:]
        if self.anchor and ok.any():
            from keyshape.base.geometry import rigid_fit
            rig = list(self.rigid)
            rot, trans, sc = rigid_fit(out[ok][:, rig], np.broadcast_to(self.reference_, (int(ok.sum()),) + self.reference_.shape),
                                       scale=True)
            out[ok] = sc[:, None, None] * np.einsum("tij,tnj->tni", rot, out[ok]) + trans[:, None]
        out[~ok] = np.nan
        return out

    def image_from_head(self, points: np.ndarray, shapes: np.ndarray | None = None) -> np.ndarray:
        """(T, 2, 3) the 2D similarity per frame nearest to taking head-frame shapes back to the image
        (on the rigid points): what 2D drawings of the head-frame shapes use."""
        from keyshape.base.geometry import rigid_fit
        p = self._check(points)
        shapes = self.transform(p) if shapes is None else shapes
        rig = list(self.rigid)
        out = np.broadcast_to(np.eye(2, 3), (len(p), 2, 3)).copy()
        ok = np.isfinite(p).all(axis=(1, 2))
        if ok.any():
            rot, trans, sc = rigid_fit(shapes[ok][:, rig], p[ok][:, rig], scale=True)
            out[ok, :, :2] = sc[:, None, None] * rot
            out[ok, :, 2] = trans
        return out

    # ------------------------------------------------------------------ KEYS.json
    def to_dict(self) -> dict:
        """The KEYS.json ``head_pose`` entry (``method: 3d``)."""
        self._fitted()
        r = lambda a: np.round(np.asarray(a, float), 6).tolist()  # noqa: E731
        return {"method": "3d", "points": list(self.rigid), "distance": self.distance, "spread": self.spread,
                "robust": self.robust, "robust_rounds": self.robust_rounds,
                "smooth": self.smooth, "adapt": self.adapt, "generic": r(self.template), "template": r(self.template_),
                "weights": r(self.weights), "focal": round(self.focal_, 6), "centre": r(self.centre_),
                "zero": r(self.zero_), "zero_frame": int(self.zero_frame_), "frame": r(self.frame_),
                "anchor": self.anchor, "reference": r(self.reference_),
                "eyeballs": list(self.eyeballs), "eye_radius": self.eye_radius}

    @classmethod
    def from_dict(cls, data: dict) -> "HeadPose3D":
        """The estimator a KEYS.json ``head_pose`` entry (``method: 3d``) describes."""
        out = cls(data["generic"], data["weights"], data["points"], data["distance"], data["smooth"], data["adapt"],
                  anchor=data["anchor"], spread=data["spread"], robust=data["robust"],
                  robust_rounds=data["robust_rounds"], eyeballs=data.get("eyeballs", ()),
                  eye_radius=data.get("eye_radius", 1.2))
        out.reference_ = np.asarray(data["reference"], np.float64)
        out.template_ = np.asarray(data["template"], np.float64)
        out.weights_ = np.asarray(data["weights"], np.float64)
        out.focal_ = float(data["focal"])
        out.centre_ = np.asarray(data["centre"], np.float64)
        out.zero_ = np.asarray(data["zero"], np.float64)
        out.zero_frame_ = int(data["zero_frame"])
        out.frame_ = np.asarray(data["frame"], np.float64)
        return out

    def __repr__(self) -> str:
        return (f"HeadPose3D(n_points={len(self.template)}, rigid={list(self.rigid)}, distance={self.distance}, "
                f"smooth={self.smooth}, adapt={self.adapt})")
