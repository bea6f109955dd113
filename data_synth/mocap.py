"""A synthetic facial-mocap take on the real ICT-FaceKit geometry, with exact dense ground truth.

Design notes and figures: docs/mocap.md, "Notes on the code", ``data_synth/mocap.py``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_dir, require_file

FACE_SKIN = 9409  # vertices 0..9408 are the face skin

# expressions driven and the role of each
EXPRESSIONS = ["jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthSmile_L", "mouthSmile_R",
               "mouthStretch_L", "mouthStretch_R", "mouthLowerDown_L", "mouthLowerDown_R", "mouthUpperUp_L",
               "mouthUpperUp_R", "eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "browInnerUp_R",
               "browOuterUp_L", "browOuterUp_R", "browDown_L", "browDown_R", "cheekSquint_L", "cheekSquint_R"]

# marker name -> Multi-PIE 68 landmark index (vertex from vertex_indices.json); x < 0 is the subject's right
LANDMARK_MARKERS = {
    "browR_1": 17, "browR_2": 18, "browR_3": 19, "browR_4": 20, "browR_5": 21,
    "browL_5": 22, "browL_4": 23, "browL_3": 24, "browL_2": 25, "browL_1": 26,
    "eyeR_outer": 36, "lidR_upper": 37, "eyeR_inner": 39, "lidR_lower": 41,
    "eyeL_inner": 42, "lidL_upper": 44, "eyeL_outer": 45, "lidL_lower": 46,
    "nose_bridge": 28, "nose_tip": 30, "nostril_R": 31, "nose_base": 33, "nostril_L": 35,
    "mouthCorner_R": 48, "lipOuterUp_R2": 49, "lipOuterUp_R1": 50, "lipOuterUp_C": 51, "lipOuterUp_L1": 52,
    "lipOuterUp_L2": 53, "mouthCorner_L": 54, "lipOuterLo_L2": 55, "lipOuterLo_L1": 56, "lipOuterLo_C": 57,
    "lipOuterLo_R1": 58, "lipOuterLo_R2": 59,
    "lipInnerUp_R1": 61, "lipInnerUp_C": 62, "lipInnerUp_L1": 63,
    "lipInnerLo_L1": 65, "lipInnerLo_C": 66, "lipInnerLo_R1": 67,
    "jawR": 5, "chinR": 7, "chin": 8, "chinL": 9, "jawL": 11,
}
# markers placed geometrically between landmarks: name -> (landmark a, landmark b, t, lift in cm along +z)
BETWEEN_MARKERS = {
    "cheekR_upper": (41, 2, 0.45, 0.0), "cheekR_mid": (31, 3, 0.5, 0.0), "cheekR_lower": (48, 4, 0.5, 0.0),
    "cheekL_upper": (46, 14, 0.45, 0.0), "cheekL_mid": (35, 13, 0.5, 0.0), "cheekL_lower": (54, 12, 0.5, 0.0),
    "nasolabialR": (31, 48, 0.5, 0.0), "nasolabialL": (35, 54, 0.5, 0.0),
    "templeR": (0, 17, 0.5, 0.0), "templeL": (16, 26, 0.5, 0.0),
}
FOREHEAD_MARKERS = {"forehead_R": -3.0, "forehead_C": 0.0, "forehead_L": 3.0}  # x in cm, 3 cm above the brows
# head-jig markers: fixed points on a headband frame (cm, head frame)
JIG = {"jig_front": (0.0, 15.5, 9.0), "jig_R": (-9.5, 11.0, 2.0), "jig_L": (9.5, 11.0, 2.0),
       "jig_top": (0.0, 17.5, 0.0), "jig_back": (0.0, 13.0, -9.0)}
RIGID_NAMES = list(JIG)


@dataclass
class FaceKit:
    """The ICT-FaceKit pieces the generator needs (centimetres)."""

    neutral: np.ndarray          # (n_vertices, 3)
    deltas: np.ndarray           # (n_expressions, n_vertices, 3)
    names: list
    landmarks: np.ndarray        # (68,) vertex indices
    triangles: np.ndarray        # (n_triangles, 3)
    folder: Path


def load_facekit(folder, names=EXPRESSIONS) -> FaceKit:
    """Read the neutral, the expression deltas ``target - neutral`` and the 68 landmark vertices."""
    from keyshape.base.formats.obj import read_obj, read_obj_vertices

    folder = require_dir(folder, "ICT-FaceKit folder")
    mesh = read_obj(require_file(folder / "generic_neutral_mesh.obj", "ICT-FaceKit neutral"))
    deltas = np.stack([read_obj_vertices(require_file(folder / f"{n}.obj", "ICT-FaceKit expression"),
                                         mesh.n_vertices) - mesh.vertices for n in names])
    meta = json.loads((folder / "vertex_indices.json").read_text())
    lm = meta["idx_to_landmark_verts"]
    lm = np.asarray(json.loads(lm) if isinstance(lm, str) else lm, dtype=np.intp)
    return FaceKit(mesh.vertices, deltas, list(names), lm, mesh.triangles, folder)


def marker_layout(kit: FaceKit, vertices: np.ndarray | None = None) -> tuple[list, np.ndarray]:
    """Names and face-skin vertex indices of the facial marker set (landmarks + in-between points)."""
    v = kit.neutral if vertices is None else vertices
    skin = v[:FACE_SKIN]
    names, idx = [], []
    for n, k in LANDMARK_MARKERS.items():
        names.append(n)
        idx.append(int(kit.landmarks[k]))
    lm = v[kit.landmarks]
    # project a wanted point onto the face skin: nearest skin vertex in (x, y) among the front-facing ones
    front = np.flatnonzero(skin[:, 2] > np.percentile(skin[:, 2], 20))

    def nearest_xy(p):
        d = np.linalg.norm(skin[front, :2] - p[:2], axis=1)
        return int(front[np.argmin(d)])

    for n, (a, b, t, _lift) in BETWEEN_MARKERS.items():
        names.append(n)
        idx.append(nearest_xy((1 - t) * lm[a] + t * lm[b]))
    brow_y = lm[17:27, 1].max()
    for n, x in FOREHEAD_MARKERS.items():
        names.append(n)
        idx.append(nearest_xy(np.array([x, brow_y + 3.0, 0.0])))
    idx = np.asarray(idx, dtype=np.intp)
    if len(set(idx.tolist())) != len(idx):
        raise InputError("marker layout: two markers landed on one vertex")
    return names, idx


def band_limited_noise(rng: np.random.Generator, n: int, rate: float, hz: float, size=()) -> np.ndarray:
    """Band-limited noise spanning [-1, 1]: a sum of random sinusoids up to ``hz``, scaled to peak 1.

    Not :func:`keyshape.data_synth.performance.smooth_noise` (Gaussian-filtered white noise of unit
    standard deviation, smoothed over a number of frames): this one is limited in hertz, so a take's
    motion does not depend on its frame rate; each synthetic data set keeps its own generator
    (changing either would change every figure measured on it).
    """
    t = np.arange(n) / rate
    k = 6
    f = rng.uniform(0.2 * hz, hz, size + (k,))
    ph = rng.uniform(0, 2 * np.pi, size + (k,))
    a = rng.uniform(0.5, 1.0, size + (k,))
    s = np.einsum("...k,...kt->...t", a, np.sin(2 * np.pi * f[..., None] * t + ph[..., None]))
    return s / np.max(np.abs(s), axis=-1, keepdims=True)


def expression_weights(n_frames: int, rate: float, rng: np.random.Generator, names=EXPRESSIONS) -> np.ndarray:
    """(n_frames, n_expressions) weights in [0, 1]: talking, blinks, smiles, brows."""
    w = np.zeros((n_frames, len(names)))
    col = {n: i for i, n in enumerate(names)}
    t = np.arange(n_frames) / rate

    def put(name, value):
        if name in col:
            w[:, col[name]] = np.clip(value, 0.0, 1.0)

    syll = np.maximum(0.0, np.sin(2 * np.pi * 2.2 * t + rng.uniform(0, 6)))  # ~4.4 syllables/s
    talk = 0.5 + 0.5 * band_limited_noise(rng, n_frames, rate, 0.3)                    # loudness envelope
    put("jawOpen", 0.75 * talk * syll ** 1.5)
    for side in "LR":
        put(f"mouthLowerDown_{side}", 0.4 * talk * syll)
        put(f"mouthUpperUp_{side}", 0.25 * talk * syll)
    put("mouthFunnel", 0.5 * np.maximum(0, band_limited_noise(rng, n_frames, rate, 1.5)))
    put("mouthPucker", 0.5 * np.maximum(0, band_limited_noise(rng, n_frames, rate, 1.5)))
    put("mouthClose", 0.3 * np.maximum(0, band_limited_noise(rng, n_frames, rate, 1.0)) * (1 - syll))
    smile = 0.5 - 0.5 * np.cos(2 * np.pi * t / 3.0 + rng.uniform(0, 2))            # one smile every 3 s
    for side, k in (("L", 1.0), ("R", 0.9)):                                        # the right side a little less
        put(f"mouthSmile_{side}", 0.8 * smile ** 2 * k)
        put(f"cheekSquint_{side}", 0.4 * smile ** 2)
    for side in "LR":                                                               # each side its own noise
        put(f"mouthStretch_{side}", 0.3 * np.maximum(0, band_limited_noise(rng, n_frames, rate, 0.8)))
    brow = np.sin(2 * np.pi * t / 2.5 + rng.uniform(0, 6))                            # raise / frown
    for side in "LR":
        put(f"browInnerUp_{side}", 0.8 * np.maximum(0, brow))
        put(f"browOuterUp_{side}", 0.6 * np.maximum(0, brow))
        put(f"browDown_{side}", 0.6 * np.maximum(0, -brow))
    # blinks: ~150 ms closures every 2-4 s
    blink = np.zeros(n_frames)
    tb = rng.uniform(0.3, 1.5)
    while tb < t[-1] + 1:
        blink = np.maximum(blink, np.exp(-0.5 * ((t - tb) / 0.04) ** 2))
        tb += rng.uniform(2.0, 4.0)
    put("eyeBlink_L", blink)
    put("eyeBlink_R", blink)
    return w


def random_head_motion(n_frames: int, rate: float, rng: np.random.Generator, degrees: float = 10.0,
                shift_cm: float = 2.0):
    """Random smooth rigid head motion ``(rot (n_frames, 3, 3), trans (n_frames, 3))``: ``world = R x + t``
    (the ground truth of a synthetic take; :func:`keyshape.retarget.headpose.head_motion` is the estimate
    from a tracker's poses)."""
    from scipy.spatial.transform import Rotation

    ang = np.deg2rad(degrees) * band_limited_noise(rng, n_frames, rate, 0.4, (3,)).T
    rot = Rotation.from_rotvec(ang).as_matrix()
    pivot = np.array([0.0, -8.0, -2.0])                      # about the neck
    trans = shift_cm * band_limited_noise(rng, n_frames, rate, 0.3, (3,)).T + pivot - np.einsum("fij,j->fi", rot, pivot)
    return rot, trans


@dataclass
class MocapTake:
    """A synthetic take. Lengths: markers in mm (as a mocap system writes), mesh in cm."""

    labels: list
    markers_mm: np.ndarray       # (n_frames, n_markers, 3) world, noisy, NaN gaps
    clean_mm: np.ndarray         # (n_frames, n_markers, 3) head frame, no noise, no gaps
    weights: np.ndarray          # (n_frames, n_expressions)
    names: list
    rot: np.ndarray
    trans_cm: np.ndarray
    marker_vertices: np.ndarray  # (n_face_markers,) vertex index of each face marker
    rate: float


def synthesize(kit: FaceKit, n_frames: int = 360, rate: float = 120.0, rng=None, noise_mm: float = 0.2,
               n_gaps: int = 6, long_gap: int = 60, head_degrees: float = 10.0) -> MocapTake:
    """Generate a take; see the module docstring. Deterministic for an int ``rng``."""
    rng = np.random.default_rng(rng)
    if n_frames < 2:
        raise InputError(f"frames: expected at least 2, got {n_frames}")
    w = expression_weights(n_frames, rate, rng, kit.names)
    # the take starts relaxed (001 section 5.1 retargets from the first frame): fade in over 0.25 s
    t = np.arange(n_frames) / rate
    w *= np.clip(t / 0.25, 0.0, 1.0)[:, None] ** 2
    names, vidx = marker_layout(kit)
    # only the marker vertices are needed per frame here: one small product
    face = kit.neutral[vidx][None] + np.einsum("fe,evc->fvc", w, kit.deltas[:, vidx])
    jig = np.array(list(JIG.values()))
    head = np.concatenate([face, np.broadcast_to(jig, (n_frames,) + jig.shape)], axis=1)
    rot, trans = random_head_motion(n_frames, rate, rng, head_degrees)
    world = np.einsum("fij,fpj->fpi", rot, head) + trans[:, None]
    labels = names + RIGID_NAMES
    noisy = world * 10.0 + rng.normal(0.0, noise_mm, world.shape)
    # gaps: short ones anywhere, one long one on a cheek marker, never on the jig
    nf = len(names)
    for _ in range(n_gaps):
        m = int(rng.integers(0, nf))
        length = int(rng.integers(2, 10))
        s = int(rng.integers(1, max(2, n_frames - length - 1)))
        noisy[s:s + length, m] = np.nan
    if long_gap and n_frames > long_gap + 20:
        m = names.index("cheekL_mid")
        s = int(rng.integers(10, n_frames - long_gap - 5))
        noisy[s:s + long_gap, m] = np.nan
    return MocapTake(labels, noisy, head * 10.0, w, list(kit.names), rot, trans, vidx, rate)


def dense_frames(kit: FaceKit, weights: np.ndarray, base: np.ndarray | None = None, out_dtype=np.float32):
    """Ground-truth meshes ``(n_frames, n_vertices, 3)`` in the head frame: one matrix product."""
    b = kit.neutral if base is None else base
    d = kit.deltas.reshape(len(kit.deltas), -1)
    return (b.reshape(1, -1) + weights @ d).reshape(len(weights), -1, 3).astype(out_dtype)


def write_take(out_dir, kit: FaceKit, perf: MocapTake, formats=("c3d", "trc")) -> dict:
    """Write markers (C3D/TRC, mm, 120 Hz), target markers JSON, rigid names and ground truth .npz atomically."""
    from keyshape.base.files import atomic_dir, atomic_path, atomic_write
    from keyshape.base.formats.markers import Markers, write_markers

    out_dir = Path(out_dir)
    paths = {}
    with atomic_dir(out_dir, kind="synth mocap take") as tmp:
        m = Markers(perf.markers_mm, perf.labels, perf.rate, "mm")
        for f in formats:
            write_markers(tmp / f"take.{f}", m)
            paths[f] = out_dir / f"take.{f}"
        nf = len(perf.marker_vertices)
        tm = {lab: int(v) for lab, v in zip(perf.labels[:nf], perf.marker_vertices)}
        with atomic_write(tmp / "target_markers.json") as fh:
            json.dump(tm, fh, indent=1)
        with atomic_write(tmp / "rigid.txt") as fh:
            fh.write(",".join(RIGID_NAMES) + "\n")
        with atomic_path(tmp / "truth.npz") as p:
            np.savez(p, weights=perf.weights, names=np.array(perf.names), rot=perf.rot, trans_cm=perf.trans_cm,
                     clean_markers_mm=perf.clean_mm, labels=np.array(perf.labels),
                     marker_vertices=perf.marker_vertices, rate=perf.rate,
                     vertices=dense_frames(kit, perf.weights))
    paths.update(target_markers=out_dir / "target_markers.json", rigid=out_dir / "rigid.txt",
                 truth=out_dir / "truth.npz")
    return paths


LOWER_LIP_MARKERS = ("lipOuterLo", "lipInnerLo", "chin", "jaw")
UPPER_LIP_MARKERS = ("lipOuterUp", "lipInnerUp", "nose", "nostril", "nasolabial")


def discontinuity_regions(kit: FaceKit, labels, split: float = 0.3) -> list:
    """Lip and eyelid mask regions on the ICT topology, as an artist would paint them.

    The vertex sets are read off the rig itself: around the mouth, vertices that
    ``jawOpen`` drops by more than ``split`` of the lower lip's drop are the lower lip and
    the others the upper lip (the mouth corners, outside 80 % of the mouth's width, stay
    unmasked as they belong to both); around each eye, vertices ``eyeBlink``
    moves by more than 30 % of its maximum are the upper lid and the still ones below
    the eye's centre the lower lid. Lower-lip vertices may not use bones touching
    upper-lip, nose or nasolabial markers and the reverse; lids likewise.
    """
    from keyshape.retarget.mocap.masks import Region

    labels = [str(s) for s in labels]
    known = set(labels)
    v = kit.neutral
    skin = np.arange(FACE_SKIN)
    out = []
    col = {n: i for i, n in enumerate(kit.names)}
    lm = v[kit.landmarks]
    if "jawOpen" in col:
        dy = kit.deltas[col["jawOpen"], :FACE_SKIN, 1]
        mouth = lm[48:68].mean(axis=0)
        width = np.ptp(lm[48:68, 0])
        area = np.linalg.norm((v[:FACE_SKIN] - mouth)[:, :2] / [0.75 * width, 0.6 * width], axis=1) < 1.0
        drop = -dy[kit.landmarks[57]]
        corners = np.abs(v[:FACE_SKIN, 0] - mouth[0]) > 0.4 * width      # the corners belong to both lips
        lower = skin[area & ~corners & (dy < -split * drop)]
        upper = skin[area & ~corners & (dy >= -split * drop)]
        out.append(Region("upper_lip", upper, {s for s in known if not s.startswith(LOWER_LIP_MARKERS)}))
        out.append(Region("lower_lip", lower, {s for s in known if not s.startswith(UPPER_LIP_MARKERS)}))
    for side, name, lids in (("R", "eyeBlink_R", slice(36, 42)), ("L", "eyeBlink_L", slice(42, 48))):
        if name not in col:
            continue
        d = np.linalg.norm(kit.deltas[col[name], :FACE_SKIN], axis=1)
        eye = lm[lids].mean(axis=0)
        width = np.ptp(lm[lids, 0])
        area = np.linalg.norm((v[:FACE_SKIN] - eye)[:, :2] / [0.9 * width, 0.6 * width], axis=1) < 1.0
        upper = skin[area & (d > 0.3 * d.max())]
        lower = skin[area & (d < 0.05 * d.max()) & (v[:FACE_SKIN, 1] < eye[1])]
        out.append(Region(f"upper_lid_{side}", upper, known - {f"lid{side}_lower"}))
        out.append(Region(f"lower_lid_{side}", lower, known - {f"lid{side}_upper"}))
    return out
