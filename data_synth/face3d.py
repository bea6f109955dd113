"""Synthetic footage of a shaded 3D head (ICT-FaceKit) with exact truth for the rig, the head and the gaze.

Design notes and figures: docs/synth.md, "Notes on the code", ``data_synth/face3d.py``.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.files import atomic_write
from keyshape.base.formats.tracks import Tracks
from keyshape.base.formats.weights import write_weights
from keyshape.base.schemes import load_scheme
from keyshape.data_synth.performance import pulse, make_performance, smooth_noise
from keyshape.base.raster import rasterize
from keyshape.data_synth.video import _check_args, render_video, select_label_frames, write_truth

#: Shapes the performance drives (ICT-FaceKit names); the curves CSV has every shape of the rig.
DRIVEN = ("jawOpen", "mouthFunnel", "mouthPucker", "mouthSmile_L", "mouthSmile_R", "eyeBlink_L", "eyeBlink_R",
          "browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R", "browDown_L", "browDown_R",
          "eyeSquint_L", "eyeSquint_R", "cheekSquint_L", "cheekSquint_R", "mouthLeft", "mouthRight",
          "eyeLookUp_L", "eyeLookUp_R", "eyeLookDown_L", "eyeLookDown_R", "eyeLookIn_L", "eyeLookIn_R",
          "eyeLookOut_L", "eyeLookOut_R")
#: Eye angle (degrees) at which an ``eyeLook*`` curve reaches 1 (horizontal, vertical).
LOOK_FULL_DEG = (30.0, 25.0)
#: Speech's jaw opening on ICT-FaceKit's ``jawOpen`` (its 1 drops the chin about 4 cm).
JAW_SCALE = 0.7
#: Head motion ranges (degrees): yaw, pitch, roll.
HEAD_RANGE_DEG = (30.0, 15.0, 10.0)
#: Eye angular radii (degrees from the eye's axis) of the pupil and the iris on the eyeball.
PUPIL_DEG, IRIS_DEG = 10.0, 23.0
#: Supersampling factor of the renderer (1: the camera blur smooths the edges; 2 costs about 3x).
SUPERSAMPLE = 1
ICT_FACE_SKIN, ICT_SOCKETS, ICT_SOCKETS_END = 9409, 11248, 14062

SIGN_CONVENTION = (
    "rig axes: x = subject's left (image-right at rest), y up, z out of the face towards the camera; "
    "world = R @ (V - pivot) + pivot + translation with R = Ry(yaw) @ Rx(pitch) @ Rz(roll), right-handed: "
    "yaw > 0 turns the face to the subject's left (nose moves image-right), pitch > 0 tips the nose down, "
    "roll > 0 is counter-clockwise on the screen (top of the head towards image-left); eye angles are "
    "relative to the head, Ry(eye_yaw) @ Rx(eye_pitch) about the eyeball centre, same signs "
    "(eye yaw > 0 looks to the subject's left, eye pitch > 0 looks down); _L/_R = the subject's left/right")


def _rot(a, axis: int) -> np.ndarray:
    """Right-handed rotations by the angles ``a`` (radians, any shape) about ``axis`` (0 x, 1 y, 2 z): (..., 3, 3)."""
    i, j = (axis + 1) % 3, (axis + 2) % 3
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(np.shape(a) + (3, 3))
    R[..., axis, axis] = 1.0
    R[..., i, i] = R[..., j, j] = c
    R[..., i, j], R[..., j, i] = -s, s
    return R


def head_rotation(yaw_deg, pitch_deg, roll_deg) -> np.ndarray:
    """``Ry(yaw) @ Rx(pitch) @ Rz(roll)`` (degrees; arrays broadcast) as (..., 3, 3)."""
    y, p, r = (np.deg2rad(np.asarray(a, dtype=np.float64)) for a in (yaw_deg, pitch_deg, roll_deg))
    return _rot(y, 1) @ _rot(p, 0) @ _rot(r, 2)


def eye_rotation(yaw_deg, pitch_deg) -> np.ndarray:
    """``Ry(yaw) @ Rx(pitch)`` (degrees) as (..., 3, 3)."""
    y, p = (np.deg2rad(np.asarray(a, dtype=np.float64)) for a in (yaw_deg, pitch_deg))
    return _rot(y, 1) @ _rot(p, 0)


def _sphere_fit(p: np.ndarray) -> tuple[np.ndarray, float]:
    a = np.c_[2 * p, np.ones(len(p))]
    s = np.linalg.lstsq(a, (p ** 2).sum(1), rcond=None)[0]
    return s[:3], float(np.sqrt(s[3] + s[:3] @ s[:3]))


def check_facekit(folder) -> Path:
    """The ICT-FaceKit folder, or :class:`InputError` naming what is missing."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("rig: expected the ICT-FaceKit folder (generic_neutral_mesh.obj and its shapes)", folder)
    need = ["generic_neutral_mesh.obj", "vertex_indices.json"] + [f"{n}.obj" for n in DRIVEN]
    missing = [n for n in need if not (folder / n).is_file()]
    if missing:
        raise InputError(f"rig: not an ICT-FaceKit folder ({', '.join(missing[:3])} missing)", folder)
    return folder


@lru_cache(maxsize=2)
def _load_facekit(folder: str):
    """Read ICT-FaceKit once per process: shape names (the rig's order), neutral mesh, identity and driven deltas."""
    from keyshape.base.formats.obj import read_obj, read_obj_vertices
    from keyshape.retarget.rig.model import _rig_files

    files, neutral_file = _rig_files(Path(folder), None)
    mesh = read_obj(neutral_file)
    if len(mesh.vertices) != 26719:
        raise InputError(f"rig: expected ICT-FaceKit's 26,719 vertices, got {len(mesh.vertices)}", neutral_file)
    base = mesh.vertices.astype(np.float64)
    ident = []
    for i in range(4):
        f = Path(folder) / f"identity{i:03d}.obj"
        ident.append(read_obj_vertices(f) - base if f.is_file() else np.zeros_like(base))
    shapes = np.stack([read_obj_vertices(Path(folder) / f"{s}.obj") - base for s in DRIVEN])
    from keyshape.retarget.rig.model import material_parts
    return tuple(f.stem for f in files), mesh, base, np.stack(ident), shapes, mesh.triangles, material_parts(mesh)


@dataclass
class _Parts:
    tri: np.ndarray          # (n, 3) rendered triangles
    eye: np.ndarray          # (n,) 0 none, 1 subject's left eye, 2 right (procedural eye colour)


class Head3D:
    """An ICT-FaceKit head ready to pose and render (loaded once; the mesh of one identity).

    Parameters
    ----------
    folder : ICT-FaceKit folder
    identity : (4,) coefficients of ``identity000..003`` (``neutral + sum c_i (identity_i - neutral)``)
    scale : uniform scale of the head
    skin : RGB skin albedo in [0, 1]

    Attributes
    ----------
    names : every shape of the rig, in :func:`keyshape.retarget.rig.model.load_rig`'s order (the curves CSV's columns)
    neutral : (n_vertices, 3) the identity's neutral, scaled
    deltas : (len(DRIVEN), n_vertices, 3) the driven shapes' deltas, scaled
    landmark_weights : (53, n_vertices) contours48 points as vertex mixes (pupil rows replaced by the iris
        centre), then its auxiliary nose points (``contours48+nose``: the iBUG-68 correspondence's vertices)
    eye_vertices : [left, right] vertex indices of each eyeball (sclera and iris shells)
    parts : the rendered triangles and which eye (1 left, 2 right, 0 none) each belongs to
    eye_centre, eye_axis, eye_radius : per eye (subject's left first), rest pose
    """

    def __init__(self, folder, identity=(0.0, 0.0, 0.0, 0.0), scale: float = 1.0, skin=(0.80, 0.62, 0.52)):
        from keyshape.retarget.rig.model import rig_landmarks, Rig

        names, mesh, base, ident, shapes, triangles, parts = _load_facekit(str(Path(check_facekit(folder)).resolve()))
        self.names = list(names)
        coef = np.asarray(identity, dtype=np.float64)
        n = base + np.tensordot(coef, ident, axes=1)
        self.scale = float(scale)
        self.identity = coef
        self.neutral = self.scale * n
        self.deltas = self.scale * shapes
        self.mesh = mesh
        rig = Rig(self.names, base, np.zeros((0, len(base), 3)), mesh)
        W, _ = rig_landmarks(rig, "contours48")
        W68, _ = rig_landmarks(rig, "ibug68")
        self.scheme = load_scheme("contours48").full()
        self.landmark_weights = np.vstack([W, W68[self.scheme.auxiliary_sources]])

        self._triangles, self._parts = triangles, parts
        # eyes: centre (sphere fit of the sclera shell), axis (towards the cornea's bulge), radius
        self.eye_centre, self.eye_axis, self.eye_radius, self.eye_vertices = [], [], [], []
        for kw in ("left", "right"):                       # material names say the subject's side
            sv = np.unique(np.concatenate([triangles[idx] for name, idx, _ in parts
                                           if "sclera" in name.lower() and kw in name.lower()]))
            c, r = _sphere_fit(self.neutral[sv])
            d = np.linalg.norm(self.neutral[sv] - c, axis=1)
            ax = self.neutral[sv[d > r + 0.5 * (d.max() - r)]].mean(0) - c
            self.eye_centre.append(c)
            self.eye_axis.append(ax / np.linalg.norm(ax))
            self.eye_radius.append(float(d.max()))
            iris = [triangles[idx] for name, idx, _ in parts if "iris" in name.lower() and kw in name.lower()]
            self.eye_vertices.append(np.unique(np.concatenate([sv] + [t.ravel() for t in iris])))
        eye_y = float(np.mean([c[1] for c in self.eye_centre]))
        # rendered: opaque materials, but the iris shell (under the sclera shell, whose pupil and iris are
        # drawn procedurally) and the lower lashes (cards lying on the lower lid that read as a black band)
        tris, eye = [], []
        lash = []
        for name, idx, rgba in parts:
            low = name.lower()
            if rgba[3] <= 0 or "iris" in low:
                continue
            t = triangles[idx]
            if "lash" in low:
                t = t[self.neutral[t, 1].mean(1) > eye_y]
                lash.append(t)
            tris.append(t)
            e = (1 if "left" in low else 2) if "sclera" in low else 0
            eye.append(np.full(len(t), e))
        self.parts = _Parts(np.concatenate(tris).astype(np.int64), np.concatenate(eye))
        from scipy.sparse import csr_matrix
        nt = len(self.parts.tri)
        self.vertex_of_triangle = csr_matrix((np.ones(3 * nt), (self.parts.tri.ravel(), np.repeat(np.arange(nt), 3))),
                                             shape=(len(self.neutral), nt))
        self.lash_vertices = np.unique(np.concatenate(lash).ravel()) if lash else np.zeros(0, np.int64)
        self.albedo = self._albedo(np.asarray(skin, dtype=np.float64))
        self.albedo32 = self.albedo.astype(np.float32)
        self.neutral32 = self.neutral.astype(np.float32)

    # ------------------------------------------------------------------ colours
    def _albedo(self, skin: np.ndarray) -> np.ndarray:
        """Per-vertex RGB albedo: skin, lips, brows, lash line, mouth interior, teeth, gums, lashes."""
        from matplotlib.path import Path as MPath

        nv = len(self.neutral)
        alb = np.tile(skin, (nv, 1))
        triangles = self._triangles
        for name, idx, rgba in self._parts:
            low = name.lower()
            if any(k in low for k in ("teeth", "gum", "tongue", "lash")):
                # inside the mouth the light is mostly blocked: gums and tongue dark, teeth dimmed
                dim = 0.8 if "teeth" in low else (0.45 if ("gum" in low or "tongue" in low) else 1.0)
                alb[np.unique(triangles[idx])] = np.asarray(rgba[:3]) * dim
        lash = (0.05, 0.035, 0.03)
        alb[self.lash_vertices] = lash
        alb[ICT_SOCKETS:ICT_SOCKETS_END] = (0.28, 0.1, 0.09)            # mouth and eye sockets
        v = self.neutral
        lm = self.landmark_weights @ v                                   # (48, 3) rest landmarks
        face = np.arange(ICT_FACE_SKIN)
        xy = v[face, :2]
        # lips: inside the outer lip contour (points 28-39), soft edge over 0.6 mm
        outer = lm[28:40, :2]
        inside = MPath(outer).contains_points(xy)
        dist = _polyline_distance(xy, np.vstack([outer, outer[:1]]))
        t = np.where(inside, 0.5 + 0.5 * np.clip(dist / 0.06, 0, 1), 0.5 - 0.5 * np.clip(dist / 0.06, 0, 1))
        lip = np.array([0.58, 0.27, 0.27])
        alb[face] = alb[face] * (1 - t[:, None]) + lip * t[:, None]
        # brows: a band about each brow's centre line (points 0-4, 5-9), wider at the inner end
        brow = np.array([0.2, 0.13, 0.09])
        for a, b, inner_first in ((0, 5, False), (5, 10, True)):        # image-left brow: its inner end is last
            line = lm[a:b, :2]
            d, s = _polyline_distance(xy, line, along=True)
            s = s if inner_first else 1 - s
            half = 0.55 - 0.25 * s                                       # cm: 5.5 mm inner, 3 mm outer
            w = np.clip((half - d) / 0.12, 0, 1) * (v[face, 2] > 2.0)
            alb[face] = alb[face] * (1 - 0.92 * w[:, None]) + brow * 0.92 * w[:, None]
        # lash line: darken the upper lid margin (points 10-14, 18-22) a little
        for a in (10, 18):
            d = _polyline_distance(xy, lm[a:a + 5, :2])
            w = np.clip((0.1 - d) / 0.06, 0, 1) * (v[face, 2] > 2.0)
            alb[face] = alb[face] * (1 - 0.7 * w[:, None]) + np.array(lash) * 0.7 * w[:, None]
        return alb

    # ------------------------------------------------------------------ posing
    def pose_vertices(self, curves: np.ndarray, eye_yaw: np.ndarray, eye_pitch: np.ndarray) -> np.ndarray:
        """Head-frame vertices (n_vertices, 3) for one frame: curves (len(DRIVEN),), eye angles (2,) (left, right)."""
        c = np.asarray(curves, dtype=np.float64)
        on = np.flatnonzero(c)
        v = self.neutral + (c[on] @ self.deltas[on].reshape(len(on), self.neutral.size)).reshape(self.neutral.shape)
        for e in range(2):
            R = eye_rotation(eye_yaw[e], eye_pitch[e])
            idx = self.eye_vertices[e]
            c = self.eye_centre[e]
            v[idx] = (v[idx] - c) @ R.T + c
        return v

    def pupils(self, eye_yaw: np.ndarray, eye_pitch: np.ndarray) -> np.ndarray:
        """(2, 3) head-frame iris centres (on the eyeball's surface, along its turned axis), left eye first."""
        out = np.empty((2, 3))
        for e in range(2):
            R = eye_rotation(eye_yaw[e], eye_pitch[e])
            out[e] = self.eye_centre[e] + self.eye_radius[e] * (R @ self.eye_axis[e])
        return out

    def landmarks3d(self, v: np.ndarray, eye_yaw, eye_pitch) -> np.ndarray:
        """(53, 3) contours48+nose points of head-frame vertices ``v`` (pupils: the iris centres)."""
        p = self.landmark_weights @ v
        pu = self.pupils(eye_yaw, eye_pitch)
        p[26], p[27] = pu[1], pu[0]            # point 26 is the image-left pupil: the subject's right eye
        return p


def _polyline_distance(p: np.ndarray, line: np.ndarray, along: bool = False):
    """Distance of points ``p`` (n, 2) to a polyline (m, 2); with ``along``, also the arc fraction of the nearest point."""
    a, b = line[:-1], line[1:]
    ab = b - a
    L = np.maximum((ab ** 2).sum(1), 1e-12)
    u = np.clip(((p[:, None] - a[None]) * ab[None]).sum(2) / L, 0, 1)      # (n, m-1)
    q = a[None] + u[..., None] * ab[None]
    d = np.linalg.norm(p[:, None] - q, axis=2)
    j = np.argmin(d, axis=1)
    dist = d[np.arange(len(p)), j]
    if not along:
        return dist
    seg = np.sqrt(L)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = (cum[j] + u[np.arange(len(p)), j] * seg[j]) / cum[-1]
    return dist, s


# ---------------------------------------------------------------------- performance

@dataclass
class Performance3D:
    """Per-frame truth of a 3D performance.

    Attributes
    ----------
    curves : (n_frames, len(DRIVEN)) driven rig curves in [0, 1]
    head_deg : (n_frames, 3) yaw, pitch, roll in degrees
    translation : (n_frames, 3) head translation in cm (camera axes = rig axes at rest)
    eye_deg : (n_frames, 2, 2) [eye (subject's left, right), (yaw, pitch)] in degrees, relative to the head
    """

    curves: np.ndarray
    head_deg: np.ndarray
    translation: np.ndarray
    eye_deg: np.ndarray

    @property
    def n_frames(self) -> int:
        return len(self.curves)


def make_performance3d(n_frames: int, fps: float, rng: np.random.Generator) -> Performance3D:
    """A talking performance on ICT-FaceKit's shapes with head turns and gaze (see the module docstring)."""
    from keyshape.data_synth.face_model import COMPONENTS

    r_perf, r_extra, r_head = rng.spawn(3)
    perf = make_performance(n_frames, fps, r_perf)
    C = {n: k for k, n in enumerate(COMPONENTS)}
    D = {n: k for k, n in enumerate(DRIVEN)}
    w = perf.weights
    cur = np.zeros((n_frames, len(DRIVEN)))
    t = np.arange(n_frames) / fps
    for name in ("mouthFunnel", "mouthPucker", "mouthSmile_L", "mouthSmile_R"):
        cur[:, D[name]] = w[:, C[name]]
    cur[:, D["jawOpen"]] = JAW_SCALE * w[:, C["jawOpen"]]     # ICT's jawOpen 1 is a 4 cm drop: speech uses less
    for side in ("L", "R"):
        cur[:, D[f"eyeBlink_{side}"]] = np.clip(w[:, C[f"eyeBlink_{side}"]] / 0.85, 0, 1)   # blinks close fully
        k = 1.0 + 0.15 * (1 if side == "L" else -1) * np.tanh(smooth_noise(n_frames, 3 * fps, r_extra))
        cur[:, D[f"browInnerUp_{side}"]] = np.clip(w[:, C["browInnerUp"]] * k, 0, 1)
        cur[:, D[f"browOuterUp_{side}"]] = w[:, C[f"browOuterUp_{side}"]]
        smile = w[:, C[f"mouthSmile_{side}"]]
        cur[:, D[f"eyeSquint_{side}"]] = 0.35 * smile
        cur[:, D[f"cheekSquint_{side}"]] = 0.5 * smile
    # frowns: slow episodes, one side stronger, not while the brows are raised
    frown = np.zeros(n_frames)
    n_ep = max(1, int(n_frames / fps / 6.0))
    for e, d in zip(r_extra.uniform(0, n_frames / fps, n_ep), r_extra.uniform(0.8, 2.0, n_ep)):
        frown = np.maximum(frown, r_extra.uniform(0.5, 1.0) * pulse(t, e, d, 0.3))
    lean = np.tanh(smooth_noise(n_frames, 2 * fps, r_extra))
    up = np.maximum(cur[:, D["browInnerUp_L"]], cur[:, D["browInnerUp_R"]])
    cur[:, D["browDown_L"]] = np.clip(frown * (1 + 0.5 * lean) * (1 - up), 0, 1)
    cur[:, D["browDown_R"]] = np.clip(frown * (1 - 0.5 * lean) * (1 - up), 0, 1)
    # the mouth sideways now and then (asymmetric)
    side = 0.35 * np.tanh(smooth_noise(n_frames, 1.5 * fps, r_extra))
    cur[:, D["mouthLeft"]] = np.clip(side, 0, 1)
    cur[:, D["mouthRight"]] = np.clip(-side, 0, 1)

    # gaze: fixations and saccades from the 2D performance (x image-right = subject's left, y down)
    eye_yaw = 25.0 * perf.gaze[:, 0]
    eye_pitch = 22.0 * perf.gaze[:, 1]
    eye = np.stack([np.stack([eye_yaw, eye_pitch], 1)] * 2, 1)            # both eyes, no vergence
    hx, vy = LOOK_FULL_DEG
    for e, side in enumerate(("L", "R")):
        out_sign = 1.0 if side == "L" else -1.0                           # the left eye looks out to the left
        yaw = eye[:, e, 0] * out_sign
        cur[:, D[f"eyeLookOut_{side}"]] = np.clip(yaw / hx, 0, 1)
        cur[:, D[f"eyeLookIn_{side}"]] = np.clip(-yaw / hx, 0, 1)
        cur[:, D[f"eyeLookDown_{side}"]] = np.clip(eye[:, e, 1] / vy, 0, 1)
        cur[:, D[f"eyeLookUp_{side}"]] = np.clip(-eye[:, e, 1] / vy, 0, 1)

    # head: a slow sweep across the yaw range, smooth wander in pitch and roll, drifting translation
    ry, rp, rr = HEAD_RANGE_DEG
    phase = r_head.uniform(0, 2 * np.pi)
    period = r_head.uniform(6.0, 9.0)
    yaw = 1.05 * ry * np.sin(2 * np.pi * t / period + phase) + 0.25 * ry * smooth_noise(n_frames, 0.8 * fps, r_head)
    pitch = 0.45 * rp * smooth_noise(n_frames, 0.9 * fps, r_head)
    roll = 0.45 * rr * smooth_noise(n_frames, 1.1 * fps, r_head)
    head = np.stack([_soft_limit(yaw, ry), _soft_limit(pitch, rp), _soft_limit(roll, rr)], 1)
    trans = np.stack([2.5 * smooth_noise(n_frames, 1.5 * fps, r_head), 1.5 * smooth_noise(n_frames, 1.5 * fps, r_head),
                      4.0 * smooth_noise(n_frames, 2.5 * fps, r_head)], 1)
    trans = np.array([4.0, 3.0, 8.0]) * np.tanh(trans / [4.0, 3.0, 8.0])
    return Performance3D(np.clip(cur, 0, 1), head, trans, eye)


def _soft_limit(x: np.ndarray, r: float) -> np.ndarray:
    """``x`` unchanged within 0.8 r, then bending smoothly (tanh) towards +-r."""
    a = np.abs(x)
    knee = 0.8 * r
    return np.sign(x) * np.where(a < knee, a, knee + (r - knee) * np.tanh((a - knee) / (r - knee)))


# ---------------------------------------------------------------------- the take

class Synthetic3D:
    """A synthetic 3D take: the truth in memory and frames rendered on demand.

    Parameters
    ----------
    rig : ICT-FaceKit folder
    frames, seed, size, fps : as ``keyshape synth video``
    identity : ``"mixed"`` (a seeded mix of the four identities, rescaled 0.94-1.06) or ``"generic"``
        (the generic neutral at scale 1)

    Attributes
    ----------
    head : Head3D
    performance : Performance3D
    focal, centre, camera_position, pivot : the camera and the head's rotation centre (cm)
    points : (n_frames, 53, 2) contours48+nose landmarks in image pixels (the nose after the 48)
    """

    def __init__(self, rig, frames: int = 300, seed: int = 0, size=(640, 480), fps: float = 30.0,
                 identity: str = "mixed", supersample: int = SUPERSAMPLE, blur: float = 0.6):
        frames, seed, size, fps = _check_args(frames, seed, size, fps)
        if identity not in ("mixed", "generic"):
            raise InputError(f"identity: expected 'mixed' or 'generic', got {identity!r}")
        self.seed, self.size, self.fps, self.identity_kind = seed, size, fps, identity
        self.supersample, self.blur = int(supersample), float(blur)
        self.head_folder = Path(rig)
        r_id, r_perf, r_look = np.random.default_rng([seed, 3]).spawn(3)
        coef = r_id.uniform(-2.5, 2.5, 4) if identity == "mixed" else np.zeros(4)
        scale = float(r_id.uniform(0.94, 1.06)) if identity == "mixed" else 1.0
        skin = np.array([0.80, 0.62, 0.52]) * r_look.uniform(0.85, 1.1) + r_look.uniform(-0.03, 0.03, 3)
        self.head = Head3D(rig, coef, scale, np.clip(skin, 0.2, 0.95))
        self.performance = make_performance3d(frames, fps, r_perf)
        w, h = size
        k = min(w / 640.0, h / 480.0)
        self.focal = 1000.0 * k
        self.centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
        self.camera_position = np.array([0.0, -1.0, 75.0])
        self.pivot = np.array([0.0, -6.0, -1.0]) * scale
        self.background = np.array([0.52, 0.56, 0.6]) * r_look.uniform(0.9, 1.1)
        self.light = np.array([-0.35, 0.45, 1.0]) / np.linalg.norm([-0.35, 0.45, 1.0])
        self.ambient = 0.3
        self.rotation = head_rotation(*self.performance.head_deg.T)
        self.points = self.project_landmarks()

    @property
    def n_frames(self) -> int:
        return self.performance.n_frames

    def _eyes(self, t):
        e = self.performance.eye_deg[t]
        return e[:, 0], e[:, 1]

    def landmarks3d(self) -> np.ndarray:
        """(n_frames, 53, 3) head-frame contours48+nose points of every frame (the vertex mixes of
        :attr:`Head3D.landmark_weights`, pupils at the turned iris centres)."""
        h = self.head
        W = h.landmark_weights
        cols = np.flatnonzero(np.abs(W).sum(0))
        v = h.neutral[cols] + np.tensordot(self.performance.curves, h.deltas[:, cols], axes=1)
        p = np.einsum("pc,ncd->npd", W[:, cols], v)
        eye = self.performance.eye_deg
        for e, row in ((0, 27), (1, 26)):      # point 26 is the image-left pupil: the subject's right eye
            R = eye_rotation(eye[:, e, 0], eye[:, e, 1])
            p[:, row] = h.eye_centre[e] + h.eye_radius[e] * (R @ h.eye_axis[e])
        return p

    def project_landmarks(self) -> np.ndarray:
        """(n_frames, 53, 2) the contours48+nose truth in image pixels (:meth:`landmarks3d` posed and projected)."""
        p = self.landmarks3d()
        world = np.einsum("nij,npj->npi", self.rotation, p - self.pivot) + self.pivot \
            + self.performance.translation[:, None]
        xy, _ = self.project(world.reshape(-1, 3))
        return xy.reshape(len(p), -1, 2)

    def world(self, v: np.ndarray, t: int) -> np.ndarray:
        """Head-frame points (n, 3) to world (camera-aligned) coordinates at frame ``t``."""
        return (v - self.pivot) @ self.rotation[t].T + self.pivot + self.performance.translation[t]

    def project(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (n, 3) to image pixels (n, 2) and depth (n,) (distance along the view axis)."""
        d = self.camera_position[2] - x[:, 2]
        u = self.centre[0] + self.focal * (x[:, 0] - self.camera_position[0]) / d
        v = self.centre[1] - self.focal * (x[:, 1] - self.camera_position[1]) / d
        return np.stack([u, v], 1), d

    def frame(self, t: int) -> np.ndarray:
        """Render frame ``t`` (BGR uint8, (height, width, 3))."""
        t = int(t)
        if not 0 <= t < self.n_frames:
            raise InputError(f"frame {t} is outside 0..{self.n_frames - 1}")
        h3 = self.head
        v = self.world(h3.pose_vertices(self.performance.curves[t], *self._eyes(t)), t)
        xy, depth = self.project(v)
        ss = self.supersample
        w, h = self.size
        W, H = w * ss, h * ss
        tri = h3.parts.tri
        frag = rasterize(ss * (xy + 0.5) - 0.5 if ss > 1 else xy, depth, tri, W, H)
        # Gouraud Lambert: area-weighted vertex normals of the posed mesh (one sparse product)
        a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
        vn = h3.vertex_of_triangle @ np.cross(b - a, c - a)
        vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
        lam = (self.ambient + (1 - self.ambient) * np.clip(vn @ self.light, 0, 1)).astype(np.float32)
        corners = tri[frag.triangle]                            # (n, 3) vertices of each fragment's triangle
        rgb = (h3.albedo32[corners] * (frag.bary * lam[corners])[:, :, None]).sum(1)
        e = h3.parts.eye[frag.triangle]
        for side in (1, 2):                                     # procedural eyes from the rest pose
            m = np.flatnonzero(e == side)
            if not len(m):
                continue
            p = (frag.bary[m, :, None] * h3.neutral32[corners[m]]).sum(1) - h3.eye_centre[side - 1]
            cosang = p @ h3.eye_axis[side - 1] / np.maximum(np.linalg.norm(p, axis=1), 1e-9)
            ang = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
            iris = np.array([0.28, 0.2, 0.13]) * (0.7 + 0.3 * np.clip((ang - PUPIL_DEG) / 6, 0, 1))[:, None]
            col = np.where((ang < PUPIL_DEG)[:, None], [0.03, 0.03, 0.035],
                           np.where((ang < IRIS_DEG)[:, None], iris, [0.93, 0.92, 0.9]))
            rgb[m] = col * (frag.bary[m] * lam[corners[m]]).sum(1)[:, None]
        img = self._background(W, H).copy()
        img.reshape(-1, 3)[frag.pixel] = np.clip(rgb[:, ::-1] * 255.0 + 0.5, 0, 255).astype(np.uint8)
        if ss > 1:
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        if self.blur > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur)
        # sensor noise: one of a few fixed noise images, chosen and shifted per frame from (seed, t)
        rng = np.random.default_rng([self.seed, 4, t])
        bank = self._noise_bank(h, w)
        k, dy, dx = int(rng.integers(len(bank))), int(rng.integers(h)), int(rng.integers(w))
        noise = np.roll(bank[k], (dy, dx), axis=(0, 1))
        return cv2.add(img.astype(np.int16), noise, dtype=cv2.CV_8U)

    def _noise_bank(self, h: int, w: int) -> np.ndarray:
        if getattr(self, "_noise", None) is None:
            rng = np.random.default_rng([self.seed, 5])
            self._noise = np.round(rng.normal(0.0, 1.5, (4, h, w, 3))).astype(np.int16)
        return self._noise

    def _background(self, W: int, H: int) -> np.ndarray:
        if getattr(self, "_bg", None) is None or self._bg.shape[:2] != (H, W):
            gy = np.linspace(1.05, 0.9, H)[:, None, None]
            self._bg = np.ascontiguousarray(np.broadcast_to(
                np.clip(gy * self.background[::-1] * 255.0 + 0.5, 0, 255).astype(np.uint8), (H, W, 3)))
        return self._bg

    # ------------------------------------------------------------------ truth
    def tracks(self) -> Tracks:
        """The landmark truth as tracks (pose: the least-squares affine from the rig's neutral front view)."""
        n = self.n_frames
        points, aux = self.head.scheme.split(self.points)                  # contours48, and the nose
        ref = self.head.landmarks3d(self.head.neutral, np.zeros(2), np.zeros(2))[:points.shape[1]]
        model = np.stack([ref[:, 0], -ref[:, 1]], 1)                       # front view, cm, y down
        A = np.c_[model, np.ones(len(model))]
        sol = np.linalg.lstsq(A, points.transpose(1, 0, 2).reshape(len(model), -1), rcond=None)[0]
        pose = sol.reshape(3, n, 2).transpose(1, 2, 0)                     # (n, 2, 3)
        return Tracks(np.arange(n), np.arange(n) / self.fps, np.ones(n), np.ones(n, bool), points, pose, {}, aux)

    def curves(self) -> np.ndarray:
        """(n_frames, len(head.names)) curves over every rig shape (undriven ones 0)."""
        out = np.zeros((self.n_frames, len(self.head.names)))
        col = {n: j for j, n in enumerate(self.head.names)}
        for i, n in enumerate(DRIVEN):
            out[:, col[n]] = self.performance.curves[:, i]
        return out

    def head_table(self) -> tuple[list[str], np.ndarray]:
        """Header and rows of ``head.csv``."""
        p = self.performance
        n = self.n_frames
        cols = ["frame", "time", "head_yaw_deg", "head_pitch_deg", "head_roll_deg", "head_tx_cm", "head_ty_cm",
                "head_tz_cm", "left_eye_yaw_deg", "left_eye_pitch_deg", "right_eye_yaw_deg", "right_eye_pitch_deg"]
        data = np.column_stack([np.arange(n), np.arange(n) / self.fps, p.head_deg, p.translation,
                                p.eye_deg[:, 0], p.eye_deg[:, 1]])
        return cols, data

    def truth(self) -> dict:
        r = lambda a, d=5: np.round(np.asarray(a, dtype=np.float64), d).tolist()  # noqa: E731
        h = self.head
        return {
            "format": "keyshape-synth-face3d/1",
            "seed": self.seed, "size": list(self.size), "fps": self.fps, "n_frames": self.n_frames,
            "scheme": "contours48",
            "rig_names": h.names,
            "identity": {"kind": self.identity_kind, "coefficients": r(h.identity), "scale": round(h.scale, 6)},
            "convention": SIGN_CONVENTION,
            "camera": {"focal_px": self.focal, "centre_px": r(self.centre), "position_cm": r(self.camera_position),
                       "looks_along": [0, 0, -1],
                       "projection": "x = cx + f * X / d, y = cy - f * (Y - cam_y) / d, d = cam_z - Z"},
            "pivot_cm": r(self.pivot),
            "eye_centre_cm": r(h.eye_centre), "eye_axis": r(h.eye_axis), "eye_radius_cm": r(h.eye_radius),
            "look_full_deg": list(LOOK_FULL_DEG),
            "head_rotation": r(self.rotation, 6),
        }

    def label_frames(self, k: int) -> np.ndarray:
        """``k`` training frames: the most neutral, the peaks of jaw, both blinks and both smiles and the
        inner brows, then farthest-point sampling over curves, gaze and head angles (a head angle at its
        range counts as much as a curve at 1), sorted."""
        p = self.performance
        peaks = [DRIVEN.index(n) for n in ("jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthSmile_L", "mouthSmile_R",
                                           "browInnerUp_L")]
        rest = [DRIVEN.index(n) for n in ("browOuterUp_R", "browDown_L", "mouthFunnel", "mouthPucker", "mouthLeft",
                                          "mouthRight")]
        feats = np.column_stack([p.curves[:, peaks], p.curves[:, rest], p.eye_deg[:, 0] / 25.0,
                                 p.head_deg / np.array(HEAD_RANGE_DEG)])
        return select_label_frames(feats, k, n_weights=len(peaks))


def synthesize(out_dir, rig, frames: int = 300, seed: int = 0, size=(640, 480), fps: float = 30.0,
               labels: int = 12, identity: str = "mixed", preview=None, verbose: bool = False) -> dict[str, Path]:
    """Write the synthetic 3D take and its truth into ``out_dir``.

    Parameters
    ----------
    out_dir : output folder (created)
    rig : ICT-FaceKit folder
    frames, seed, size, fps, labels : as :func:`keyshape.data_synth.video.synthesize`
    identity : ``"mixed"`` or ``"generic"`` (see :class:`Synthetic3D`)
    preview : optional PNG contact sheet with the truth drawn
    verbose : progress on standard error

    Returns
    -------
    dict with paths ``video``, ``truth`` (tracks CSV of the contours48 landmarks), ``curves`` (the rig's
    curves, ``frame`` + every shape name, as ``retarget --poses --rig -o curves.csv`` writes), ``head``
    (head and eye angles, translation), ``labels`` (folder of ``NNNNNN.pts``), ``truth_json`` and, when
    asked, ``preview``.
    """
    frames, seed, size, fps = _check_args(frames, seed, size, fps, labels)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sv = Synthetic3D(rig, frames, seed, size, fps, identity)
    paths = {"video": out / "video.mp4", "truth": out / "truth.csv", "curves": out / "curves.csv",
             "head": out / "head.csv", "labels": out / "labels", "truth_json": out / "truth.json"}
    kept = render_video(paths["video"], sv.frame, frames, fps, size, preview, "synth face3d", verbose)
    write_weights(paths["curves"], np.arange(frames), sv.head.names, sv.curves())
    cols, data = sv.head_table()
    with atomic_write(paths["head"]) as f:
        f.write(",".join(cols) + "\n")
        f.write("\n".join(",".join([str(int(r[0]))] + ["%.6f" % x for x in r[1:]]) for r in data) + "\n")
    write_truth(paths, sv, labels, preview, kept, write_preview)
    return paths


def write_preview(path, sv: Synthetic3D, frames: dict[int, np.ndarray], tile_width: int = 400) -> Path:
    """Contact sheet of ``frames`` (index -> image) as face close-ups with the truth drawn (PNG), captioned
    with each frame's head angles (:func:`keyshape.data_synth.video.write_preview`)."""
    from keyshape.data_synth.video import write_preview as sheet

    def caption(t: int) -> str:
        y, p, r = sv.performance.head_deg[t]
        return f"frame {t}: yaw {y:+.0f} pitch {p:+.0f} roll {r:+.0f}"

    return sheet(path, sv, frames, tile_width, caption)
