"""A rig's scheme landmarks from what rigs publish (iBUG-68 vertex lists), checked, or found on the rig itself.

Three things a rig of any topology needs before ``keyshape solve`` can drive it:

* :func:`contours48_from_ibug68`: the ``contours48`` points from the 68 iBUG (Multi-PIE) landmarks that
  rigs publish (ICT-FaceKit's ``vertex_indices.json``, Apple's ARKit face mesh list), exactly as the
  shipped ICT-FaceKit file ``retarget/data/ict_landmarks_contours48.json`` was made
  (``bench/build_ict_landmarks.py``): brows = iBUG 17-21 and 22-26; each eye's six iBUG points
  (corner, two upper-lid points, corner, two lower-lid points) resampled to eight, the 3 upper and
  3 lower lid points at 1/4, 1/2 and 3/4 of the lid polyline's arc length (corner, two lid landmarks,
  corner) as weighted pairs of vertices; the pupils: the eyeball's front vertex, or, on a rig
  without eyeballs (a face mask), the midpoint of the eye's corners (they then move with no shape:
  gaze goes only to Live Link's eye angles); lips = iBUG 48-67 one to one.
* :func:`landmark_problem`: what is wrong with a correspondence on this rig (wrong count; points in
  the wrong order, e.g. iBUG's first 48 points given as a ``contours48`` file), read from geometry.
* :func:`find_ibug68`: the 68 iBUG points found on a rig with no correspondence: ICT-FaceKit's face
  (the shipped subset) is brought onto the rig's neutral by the similarity that maps the regions the
  rig's own shapes move (each ``eyeBlink`` = a lid, ``jawOpen`` = the jaw and lower lip,
  ``browInnerUp`` = the brows; ARKit and ICT names in either spelling) onto ICT's, and each of ICT's
  landmarks is then placed on the nearest point of the rig's surface that moves as the landmark
  does under those shapes (an upper lip point on the upper lip, which ``jawOpen`` leaves, not on the
  lower lip it touches in a closed-mouth neutral).

Pure functions over arrays: no file is opened here (:mod:`keyshape.base.formats.poses` reads and writes).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: each eye's six iBUG-68 points start at these indices (image-left eye first: the subject's right)
IBUG_EYES = (36, 42)
#: contours48's lid points between the corners, as fractions of the lid's arc length
LID_FRACTIONS = (0.25, 0.5, 0.75)
#: ICT-FaceKit's eye, corner to corner (cm): the scale of :data:`PUPIL_RADIUS`
ICT_EYE_WIDTH = 2.687
#: the pupil vertex lies within this fraction of the eye's width of the eye's centre (front view)
PUPIL_RADIUS = 0.3 / ICT_EYE_WIDTH
#: a vertex moved by less than this fraction of the eye's width by a shape is still under it
STILL = 1e-5


def one_hot(indices: Sequence[int], n_vertices: int) -> np.ndarray:
    """(n, n_vertices) weight rows of single vertices."""
    idx = np.asarray(indices, np.intp)
    W = np.zeros((len(idx), n_vertices))
    W[np.arange(len(idx)), idx] = 1.0
    return W


def lid_rows(W: np.ndarray, neutral: np.ndarray, fractions: Sequence[float] = LID_FRACTIONS) -> np.ndarray:
    """Weight rows of the points at arc-length ``fractions`` along the polyline of the points ``W`` (k, n_vertices).

    Each result row blends the two rows of the segment it falls on, ``(1 - a) W[j] + a W[j + 1]``.
    """
    p = W @ neutral
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)]) / seg.sum()
    f = np.asarray(fractions, np.float64)
    j = np.minimum(np.searchsorted(s, f, side="right") - 1, len(W) - 2)
    a = (f - s[j]) / (s[j + 1] - s[j])
    return (1 - a)[:, None] * W[j] + a[:, None] * W[j + 1]


def eye_width(W68: np.ndarray, neutral: np.ndarray) -> float:
    """Mean corner-to-corner width of the two eyes of iBUG-68 weight rows."""
    p = W68 @ neutral
    return float(np.mean([np.linalg.norm(p[e + 3] - p[e]) for e in IBUG_EYES]))


def pupil_vertex(neutral: np.ndarray, eye6: np.ndarray, still: np.ndarray, width: float) -> int | None:
    """The eyeball's front vertex before an eye: of the vertices no lid shape moves (``still``) within
    :data:`PUPIL_RADIUS` eye widths of the eye's centre in the front view and in front of it, the
    foremost; None when there is none (a rig without eyeballs)."""
    c = eye6.mean(axis=0)
    near = np.flatnonzero(still & (np.linalg.norm(neutral[:, :2] - c[:2], axis=1) < PUPIL_RADIUS * width)
                          & (neutral[:, 2] > c[2]))
    return int(near[np.argmax(neutral[near, 2])]) if len(near) else None


@dataclass
class Derived:
    """A scheme's points derived on a rig: ``W`` (n_points, n_vertices) rows summing to 1, and what the
    derivation had to decide (``notes``: one line each, for the user)."""

    W: np.ndarray
    notes: list


def contours48_from_ibug68(W68: np.ndarray, neutral: np.ndarray, still: np.ndarray | None = None) -> Derived:
    """contours48's 48 points from iBUG-68's 68 (see the module docstring), as weight rows.

    Parameters
    ----------
    W68 : (68, n_vertices) the iBUG points as weight rows (:func:`one_hot` of a published vertex list)
    neutral : (n_vertices, 3) the rig's neutral, front view along +z, y up (the solve's view)
    still : (n_vertices,) bool, vertices that no shape moves but gaze shapes (the eyeballs of a rig that
        turns them with bones); None: the rig has no eyeballs

    Returns
    -------
    Derived, with ``W`` (48, n_vertices); on ICT-FaceKit the shipped file's points to 1e-6.
    """
    W68 = np.asarray(W68, np.float64)
    rows = [W68[17:27]]                                                       # 0-9 brows
    for e in IBUG_EYES:                                                        # 10-17, 18-25 eyes
        c0, u1, u2, c1, l1, l2 = W68[e:e + 6]
        rows += [c0[None], lid_rows(np.stack([c0, u1, u2, c1]), neutral), c1[None],
                 lid_rows(np.stack([c1, l1, l2, c0]), neutral)]
    width = eye_width(W68, neutral)
    notes = []
    pupils = []
    for e in IBUG_EYES:                                                        # 26, 27 pupils
        v = None if still is None else pupil_vertex(neutral, W68[e:e + 6] @ neutral, still, width)
        pupils.append(one_hot([v], len(neutral))[0] if v is not None else 0.5 * (W68[e] + W68[e + 3]))
    if still is None or any(p.max() < 1 for p in pupils):
        notes.append("the rig has no eyeballs: its pupils are put between each eye's corners and move with no "
                     "shape, so the gaze goes only to Live Link's eye angles (and eyeLook* shapes with --gaze shapes)")
    rows.append(np.stack(pupils))
    rows.append(W68[48:68])                                                   # 28-47 lips
    return Derived(np.concatenate(rows), notes)


def still_vertices(deltas: np.ndarray, names: Sequence[str], width: float) -> np.ndarray:
    """(n_vertices,) bool: vertices that no shape but the gaze shapes (``eyeLook*``) moves by
    :data:`STILL` eye widths or more (the eyeballs of a rig that turns them with bones; the back of the head)."""
    keep = [j for j, n in enumerate(names) if not n.lower().startswith("eyelook")]
    if not keep:
        return np.ones(deltas.shape[1], bool)
    return np.abs(deltas[keep]).max(axis=(0, 2)) < STILL * width


def landmark_problem(points: np.ndarray, scheme, centroid: np.ndarray | None = None) -> str | None:
    """What is wrong with a scheme's points on a rig, read from their geometry; None when nothing is.

    Checked for a scheme with contours48's contours (others pass): each eye's and each lip contour's
    points lie together (the contour spans less than the distance between the eyes' centres, the pupil
    within an eye's width of its contour), the brows are nearer the eyes than the mouth, each brow
    nearer its own eye, the upper lids and the upper lips above the lower ones (up: from the mouth
    to the eyes), and the image-left eye is the subject's right (with ``centroid``, the rig's vertex
    centroid, behind the face). The 68 iBUG points given as a 48-point file fail the first check
    (their points 10-17 are the jaw line and a brow end).

    Parameters
    ----------
    points : (n_points, 3) the scheme's points on the rig's neutral
    scheme : :class:`keyshape.base.schemes.Scheme`
    centroid : (3,) the rig's vertex centroid, or None (the left-right check is skipped)
    """
    c = scheme.contours
    need = ("brow_left", "brow_right", "eye_left", "eye_right", "pupil_left", "pupil_right", "lip_outer", "lip_inner")
    if not all(k in c for k in need):
        return None
    P = np.asarray(points, np.float64)
    at = {k: P[list(c[k])] for k in need}
    mid = {k: v.mean(axis=0) for k, v in at.items()}
    between = float(np.linalg.norm(mid["eye_right"] - mid["eye_left"]))
    if not between > 0:
        return "the two eyes' points coincide"
    for k in ("eye_left", "eye_right", "lip_outer", "lip_inner"):
        span = float(np.linalg.norm(at[k][:, None] - at[k][None], axis=-1).max())
        if span > between:
            return (f"the {k.replace('_', ' ')} points {c[k][0]}-{c[k][-1]} are not one contour (they span {span:.3g}, "
                    f"more than the {between:.3g} between the eyes): points in another order (iBUG-68's 68 "
                    "given as a contours48 file?)")
    for side in ("left", "right"):
        e = at[f"eye_{side}"]
        if np.linalg.norm(mid[f"pupil_{side}"] - e.mean(axis=0)) > np.linalg.norm(e[0] - e[4]):
            return f"the {side} pupil (point {c[f'pupil_{side}'][0]}) is not within its eye"
    mouth = 0.5 * (mid["lip_outer"] + mid["lip_inner"])
    eyes = 0.5 * (mid["eye_left"] + mid["eye_right"])
    for side, other in (("left", "right"), ("right", "left")):
        b = mid[f"brow_{side}"]
        if np.linalg.norm(b - mouth) < np.linalg.norm(b - eyes):
            return f"the {side} brow's points are nearer the mouth than the eyes"
        if np.linalg.norm(b - mid[f"eye_{other}"]) < np.linalg.norm(b - mid[f"eye_{side}"]):
            return f"the {side} brow's points are nearer the {other} eye than the {side} one"
    up = eyes - mouth
    up /= np.linalg.norm(up)
    for k, upper, lower in (("eye_left", (1, 2, 3), (5, 6, 7)), ("eye_right", (1, 2, 3), (5, 6, 7)),
                            ("lip_outer", (1, 2, 3, 4, 5), (7, 8, 9, 10, 11)), ("lip_inner", (1, 2, 3), (5, 6, 7))):
        h = at[k] @ up
        if h[list(upper)].mean() < h[list(lower)].mean():
            return f"the {k.replace('_', ' ')}'s upper points are below its lower ones"
    if centroid is not None:
        right = mid["eye_right"] - mid["eye_left"]
        front = np.cross(right, up)
        if front @ (eyes - np.asarray(centroid, np.float64)) < 0:
            return ("the image-left eye's points (10-17) are on the subject's left: contours48 puts the subject's "
                    "right first (image-left)")
    return None


#: the rig shapes (ARKit/ICT name keys, :func:`keyshape.retarget.targets.target_set.name_key`) whose motion finds the
#: face: each feature is the sum of its shapes' deltas; the first three are required
FEATURES = {"blink_left": ("eyeblinkleft",), "blink_right": ("eyeblinkright",), "jaw": ("jawopen",),
            "brows": ("browinnerup", "browinnerupleft", "browinnerupright"),
            "smile_left": ("mouthsmileleft",), "smile_right": ("mouthsmileright",)}
REQUIRED = ("blink_left", "blink_right", "jaw")
#: the shapes' names as a user would look for them
SPELLED = {"blink_left": "eyeBlinkLeft (eyeBlink_L)", "blink_right": "eyeBlinkRight (eyeBlink_R)", "jaw": "jawOpen"}
#: the features whose motion tells the surfaces apart where they touch (lips, lids)
TELLING = ("jaw", "blink_left", "blink_right")


def feature_deltas(deltas: np.ndarray, names: Sequence[str]) -> dict[str, np.ndarray]:
    """{feature: (n_vertices, 3) summed deltas} of the :data:`FEATURES` the rig has (by name, either spelling)."""
    from keyshape.retarget.targets.target_set import name_key
    keys = [name_key(n) for n in names]
    out = {}
    for f, wanted in FEATURES.items():
        idx = [j for j, k in enumerate(keys) if k in wanted]
        if idx:
            out[f] = np.asarray(deltas, np.float64)[idx].sum(axis=0)
    return out


def face_axes(neutral: np.ndarray, deltas: np.ndarray, names: Sequence[str], clear: float = 0.8) -> np.ndarray | None:
    """The axis-aligned rotation taking a rig to the solve's view (x to the subject's left, y up, z to the
    viewer), read from its shapes: right = the left blink's centroid less the right's, up = from the
    jawOpen region to the eyes (made orthogonal to right), front = right x up; each snapped to the
    nearest signed axis. None when the rig lacks those shapes or an axis is not clear (its largest
    component under ``clear``)."""
    f = feature_deltas(deltas, names)
    if not all(k in f for k in REQUIRED):
        return None
    V = np.asarray(neutral, np.float64)
    w = {k: np.linalg.norm(f[k], axis=1) ** 2 for k in REQUIRED}
    c = {k: (w[k][:, None] * V).sum(axis=0) / max(w[k].sum(), 1e-300) for k in REQUIRED}
    right = c["blink_left"] - c["blink_right"]
    up = 0.5 * (c["blink_left"] + c["blink_right"]) - c["jaw"]
    nr = np.linalg.norm(right)
    if not nr > 0:
        return None
    right = right / nr
    up = up - (up @ right) * right
    nu = np.linalg.norm(up)
    if not nu > 0:
        return None
    up = up / nu
    axes = np.stack([right, up, np.cross(right, up)])
    if (np.abs(axes).max(axis=1) < clear).any():
        return None
    R = np.zeros((3, 3))
    k = np.argmax(np.abs(axes), axis=1)
    if len(set(k.tolist())) < 3:
        return None
    R[np.arange(3), k] = np.sign(axes[np.arange(3), k])
    return R


def vertex_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(n_vertices,) a third of the area of the triangles around each vertex."""
    t = np.asarray(triangles, np.intp)
    a = 0.5 * np.linalg.norm(np.cross(vertices[t[:, 1]] - vertices[t[:, 0]], vertices[t[:, 2]] - vertices[t[:, 0]]),
                             axis=1)
    return np.bincount(t.ravel(), np.repeat(a / 3, 3), minlength=len(vertices))


def feature_centroid(vertices: np.ndarray, delta: np.ndarray, area: np.ndarray) -> np.ndarray:
    """Where a shape acts: the centroid of the vertices it moves by over a quarter of its largest motion,
    each weighted by its area and its motion squared (independent of how densely the mesh is sampled)."""
    m = np.linalg.norm(delta, axis=1)
    w = area * m ** 2 * (m > 0.25 * m.max())
    return (w[:, None] * vertices).sum(axis=0) / w.sum()


def _motion_scale(delta: np.ndarray) -> float:
    m = float(np.linalg.norm(delta, axis=1).max())
    return m if m > 0 else 1.0


def _closest_on_triangles(p: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points to ``p`` (3,) on triangles (n, 3) x3: (n,) distances and (n, 3) barycentric weights."""
    ab, ac, ap = B - A, C - A, p - A
    d00, d01, d11 = (ab * ab).sum(1), (ab * ac).sum(1), (ac * ac).sum(1)
    d20, d21 = (ap * ab).sum(1), (ap * ac).sum(1)
    den = np.maximum(d00 * d11 - d01 ** 2, 1e-30)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bary = np.stack([1 - v - w, v, w], 1)
    inside = (bary >= 0).all(axis=1)
    cands = [bary]
    for i, j in ((0, 1), (1, 2), (2, 0)):                                 # the edges' closest points
        P = np.stack([A, B, C])
        e = P[j] - P[i]
        t = np.clip(((p - P[i]) * e).sum(1) / np.maximum((e * e).sum(1), 1e-30), 0, 1)
        b = np.zeros((len(A), 3))
        b[:, i], b[:, j] = 1 - t, t
        cands.append(b)
    pts = [b[:, :1] * A + b[:, 1:2] * B + b[:, 2:] * C for b in cands]
    dist = np.stack([np.linalg.norm(q - p, axis=1) for q in pts], 1)
    dist[:, 0] = np.where(inside, dist[:, 0], np.inf)
    k = np.argmin(dist, axis=1)
    return dist[np.arange(len(A)), k], np.stack(cands, 1)[np.arange(len(A)), k]


def _shared_motion(ref_deltas, ref_names, deltas, names, rot, n_dims):
    """Both faces' motion under every shape they share by name (gaze shapes aside), each shape's motion
    relative to its largest on its own face, the reference's turned into the rig's axes, reduced to
    their ``n_dims`` principal components: (n_ref, n_dims), (n_vertices, n_dims)."""
    from keyshape.retarget.targets.target_set import name_key
    rk = {name_key(n): j for j, n in enumerate(ref_names) if not n.lower().startswith("eyelook")}
    pairs = [(rk[name_key(n)], j) for j, n in enumerate(names) if name_key(n) in rk]
    a = np.concatenate([(ref_deltas[i] @ rot.T) / _motion_scale(ref_deltas[i]) for i, _ in pairs], 1)
    b = np.concatenate([deltas[j] / _motion_scale(deltas[j]) for _, j in pairs], 1)
    if a.shape[1] <= n_dims:
        return a, b
    _, _, vt = np.linalg.svd(np.concatenate([a, b]), full_matrices=False)
    basis = vt[:n_dims].T                             # drops the components both faces hardly use
    return a @ basis, b @ basis


def skin_triangles(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """The triangles of the mesh's largest connected piece (by triangle count): a face's skin, where
    eyeballs, teeth, the tongue and the shells around the eyes are pieces of their own."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    t = np.asarray(triangles, np.intp)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]]])
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    _, label = connected_components(g, directed=False)
    piece = label[t[:, 0]]
    return t[piece == np.bincount(piece).argmax()]


def used_vertices(triangles: np.ndarray) -> np.ndarray:
    """The vertices some triangle uses (sorted)."""
    return np.unique(np.asarray(triangles, np.intp))


def _smooth_step(Y: np.ndarray, dy: np.ndarray, V: np.ndarray, dv: np.ndarray, eyes: float,
                 n_centres: int = 150, width: float = 0.35, ridge: float = 1e-2, symmetric: bool = True) -> np.ndarray:
    """One non-rigid ICP step: each reference point ``Y`` goes toward its nearest rig point in position and
    motion (``dy``, ``dv``), pairs further than three times the median dropped; the displacement is a sum of
    Gaussians ``width`` eye distances wide on ``n_centres`` reference points (ridge ``ridge``), so it is smooth."""
    from scipy.spatial import cKDTree
    a, b = np.concatenate([Y, dy], 1), np.concatenate([V, dv], 1)
    _, nn = cKDTree(b).query(a)                                           # each reference point's rig point
    src, r = np.arange(len(Y)), V[nn] - Y
    if symmetric:                                                         # and each rig point's reference point
        _, back = cKDTree(a).query(b)
        src, r = np.concatenate([src, back]), np.concatenate([r, V - Y[back]])
    dist = np.linalg.norm(r, axis=1)
    ok = dist < 3 * np.median(dist) + 1e-12
    rng = np.random.default_rng(0)
    C = Y[rng.choice(len(Y), min(n_centres, len(Y)), replace=False)]
    sig = width * eyes
    phi = np.exp(-0.5 * (np.linalg.norm(Y[:, None] - C[None], axis=-1) / sig) ** 2)
    A = phi[src[ok]]
    coef = np.linalg.solve(A.T @ A + ridge * len(A) * np.eye(len(C)), A.T @ r[ok])
    return phi @ coef


@dataclass(frozen=True)
class FitOptions:
    """The landmark search's settings (:func:`find_ibug68`), chosen on the remeshed test rigs
    (``bench/rig_landmarks_accuracy.py``)."""

    widths: Sequence[float] = tuple(np.linspace(0.5, 0.1, 14))
    ridge: float = 1e-2
    n_dims: int = 16
    motion_weight: float = 0.6
    face_margin: float = 0.35
    symmetric: bool = True
    skin_only: bool = True
    side_tolerance: float = 0.25
    corner_radius: float = 0.03


def find_ibug68(neutral: np.ndarray, deltas: np.ndarray, names: Sequence[str], triangles: np.ndarray,
                reference, options: FitOptions = FitOptions()) -> np.ndarray:
    """The 68 iBUG points found on a rig with no correspondence, as (68, n_vertices) weight rows.

    ``reference``: a face with known iBUG-68 vertices and the same :data:`FEATURES` (the shipped
    ICT-FaceKit subset, :func:`keyshape.retarget.targets.demo.load_expressions`).

    0. With ``skin_only``, the rig's skin alone is used (:func:`skin_triangles`: its largest connected
       piece; eyeballs, teeth, the tongue and the eye shells, and their motion, are left out).
    1. The reference's feature centroids (:func:`feature_centroid`: the regions the blinks, jawOpen,
       browInnerUp and the smiles move) are mapped onto the rig's by a similarity (Umeyama): it takes
       the rig's units and axes.
    2. The reference's face (its vertices within ``face_margin`` eye distances of its landmarks: no
       scalp, ears or neck, which a face mask lacks) is fitted onto the rig by non-rigid ICP: each
       reference point and (``symmetric``) each rig vertex is paired with its nearest point of the other
       face in position and motion (:func:`_shared_motion`: how every shape the two faces share by name
       moves it, each relative to its largest, times ``motion_weight`` eye distances), pairs beyond three
       times the median distance dropped; the displacement is a ridge-regularised sum of Gaussians on 150
       reference points, ``widths`` eye distances wide, one width per iteration, from coarse to fine.
    3. Each fitted landmark goes to the nearest point of the rig's surface that moves as it does under the
       :data:`TELLING` shapes (jawOpen, the blinks), the motion choosing the surface only (an upper-lip point
       lands on the upper lip that jawOpen leaves, not on the lower lip it touches in a closed-mouth
       neutral); the inner mouth corners, where the lips meet, by position and by where jawOpen's motion lies
       between the lips' around them (:func:`place_landmarks`).

    Measured on remeshed ICT-FaceKit rigs (``bench/rig_landmarks_accuracy.py``, docs/benchmarks.md).

    Raises
    ------
    ValueError
        The rig lacks a required feature's shape (blinks, jawOpen).
    """
    widths, ridge, n_dims, motion_weight = options.widths, options.ridge, options.n_dims, options.motion_weight
    face_margin, symmetric, skin_only = options.face_margin, options.symmetric, options.skin_only
    from scipy.spatial import cKDTree

    from keyshape.base.geometry import rigid_fit
    V = np.asarray(neutral, np.float64)
    tri = np.asarray(triangles, np.intp)
    fr = feature_deltas(reference.deltas, reference.names)
    fg = feature_deltas(deltas, names)
    missing = [f for f in REQUIRED if f not in fg]
    if missing:
        raise ValueError(f"the rig has no {SPELLED[missing[0]]} shape to find its face by")
    common = [f for f in FEATURES if f in fg and f in fr]
    if skin_only:                                     # the face's skin: no eyeballs, teeth, tongue or eye shells
        tri = skin_triangles(tri, len(V))
        off = np.ones(len(V), bool)
        off[used_vertices(tri)] = False
        if off.any():                                 # their motion is not the skin's (motion scales, pairs)
            deltas = np.where(off[None, :, None], 0.0, np.asarray(deltas, np.float64))
            fg = feature_deltas(deltas, names)
    ar, ag = vertex_areas(reference.neutral, reference.triangles), vertex_areas(V, tri)
    src = np.stack([feature_centroid(reference.neutral, fr[f], ar) for f in common])
    dst = np.stack([feature_centroid(V, fg[f], ag) for f in common])
    rot, trans, scale = (x[0] for x in rigid_fit(src, dst[None], scale=True))
    lm = np.asarray(reference.landmarks, np.intp)
    eyes = float(np.linalg.norm(dst[common.index("blink_left")] - dst[common.index("blink_right")]))
    L = motion_weight * eyes
    desc_ref = np.concatenate([(fr[f] @ rot.T) / _motion_scale(fr[f]) for f in TELLING], 1) * L
    desc_rig = np.concatenate([fg[f] / _motion_scale(fg[f]) for f in TELLING], 1) * L
    Y = scale * reference.neutral @ rot.T + trans
    match_ref, match_rig = _shared_motion(reference.deltas, reference.names, deltas, names, rot, n_dims)
    match_ref, match_rig = match_ref * L, match_rig * L
    used = used_vertices(tri)
    # the reference's face (its points near its landmarks): no scalp, ears or neck, which a face mask lacks
    face = np.flatnonzero(cKDTree(Y[lm]).query(Y)[0] < face_margin * eyes)
    at = np.searchsorted(face, lm)
    Y, match_ref = Y[face], match_ref[face]
    for w in widths:
        Y = Y + _smooth_step(Y, match_ref, V[used], match_rig[used], eyes, width=w, ridge=ridge, symmetric=symmetric)
    eyes_ref = float(np.linalg.norm(src[common.index("blink_left")] - src[common.index("blink_right")]))
    corners = corner_fractions(reference.neutral, fr["jaw"], lm, eyes_ref, options.corner_radius)
    return place_landmarks(Y[at], desc_ref[lm], V, tri, desc_rig, eyes, corners, options)

#: iBUG-68's inner mouth corners: where jawOpen's separation of the lips begins
INNER_CORNERS = (60, 64)


def _candidates(target: np.ndarray, V: np.ndarray, tri: np.ndarray, desc: np.ndarray, k: int = 64):
    """For each target point, the closest points on the triangles around its ``k`` nearest vertices:
    [(triangles (m, 3), distances (m,), barycentric weights (m, 3), motion descriptors (m, d))]."""
    from scipy.spatial import cKDTree
    used = used_vertices(tri)
    _, near = cKDTree(V[used]).query(target, k=min(k, len(used)))
    order = np.argsort(tri.ravel(), kind="stable")
    starts = np.searchsorted(tri.ravel()[order], np.arange(len(V) + 1))
    out = []
    for p, vs in zip(target, used[near]):                                 # 68 points
        t = tri[np.unique(np.concatenate([order[starts[v]:starts[v + 1]] // 3 for v in vs]))]
        dist, bary = _closest_on_triangles(p, V[t[:, 0]], V[t[:, 1]], V[t[:, 2]])
        out.append((t, dist, bary, np.einsum("tk,tkd->td", bary, desc[t])))
    return out


def separation(vertices: np.ndarray, jaw: np.ndarray, centre: np.ndarray, radius: float) -> tuple[np.ndarray, float, float]:
    """How jawOpen separates the lips around ``centre``: its motion ``jaw`` (n, 3) at the ``vertices`` (n, 3)
    within ``radius`` of it, along their mean direction: (that direction, the least and the largest motion)."""
    near = np.linalg.norm(vertices - centre, axis=1) < radius
    u = jaw[near].mean(axis=0)
    u = u / max(float(np.linalg.norm(u)), 1e-300)
    m = jaw[near] @ u
    return u, float(m.min()), float(m.max())


def corner_fractions(neutral: np.ndarray, jaw: np.ndarray, landmarks: np.ndarray, eyes: float,
                     radius: float) -> dict[int, float]:
    """{iBUG point: where its jawOpen motion lies between the least and the largest of the vertices within
    ``radius`` eye distances (``eyes``) of it (0: with the upper lip, 1: with the lower)} for the inner mouth
    corners (:data:`INNER_CORNERS`) of a reference face: ``neutral`` (n, 3), its jawOpen deltas ``jaw``
    (n, 3), its iBUG-68 vertices ``landmarks``."""
    out = {}
    for i in INNER_CORNERS:
        c = int(landmarks[i])
        u, lo, hi = separation(neutral, jaw, neutral[c], radius * eyes)
        out[i] = float(np.clip((jaw[c] @ u - lo) / max(hi - lo, 1e-300), 0.0, 1.0))
    return out


def place_landmarks(target: np.ndarray, desc_ref: np.ndarray, V: np.ndarray, tri: np.ndarray, desc_rig: np.ndarray,
                    eyes: float, corners: dict[int, float], options: FitOptions = FitOptions()) -> np.ndarray:
    """Step 3 of :func:`find_ibug68`: the fitted iBUG points ``target`` (68, 3) put on the rig's surface, as
    (68, n_vertices) weight rows.

    ``desc_ref`` (68, 3 t) and ``desc_rig`` (n_vertices, 3 t): how the :data:`TELLING` shapes (jawOpen first)
    move each landmark and each rig vertex, relative to each shape's largest motion on its own face, times
    ``options.motion_weight`` eye distances; ``eyes``: the distance between the eyes; ``corners``: the
    reference's inner mouth corners' :func:`corner_fractions`.

    1. The surface a landmark lies on: of the closest points to it on the triangles around its 64 nearest
       vertices, those whose motion is within ``options.side_tolerance`` (of the largest motion) of the
       best match's: the upper lip that jawOpen leaves, not the lower lip an upper-lip point touches in a
       closed-mouth neutral; the upper lid, not the lower one. The landmark goes to the nearest of them in
       position: the motion only chooses the surface, since another artist's shapes move it by other
       amounts.
    2. The inner mouth corners (:data:`INNER_CORNERS`), where the lips meet and the vertices of both lips and
       of the corner lie within a fraction of a millimetre of each other, each moved by jawOpen as its own
       lip: the point nearest in position and in jawOpen's motion to the motion that lies where the
       reference's corner lies between its lips' (:func:`corner_fractions`), among the rig's vertices within
       ``options.corner_radius`` eye distances of the fitted corner: a fraction, so neither the motion's
       amount (another artist's) nor the fit's last fraction of a millimetre matters.
    """
    L = options.motion_weight * eyes
    cand = _candidates(target, V, tri, desc_rig)
    W = np.zeros((len(target), len(V)))
    for i, (t, dist, bary, desc) in enumerate(cand):                     # 68 points
        c = np.linalg.norm(desc - desc_ref[i], axis=1)
        ok = np.flatnonzero(c <= c.min() + options.side_tolerance * L)
        j = ok[np.argmin(dist[ok])]
        np.add.at(W[i], t[j], bary[j])
    used = used_vertices(tri)
    for i, frac in corners.items():
        u, lo, hi = separation(V[used], desc_rig[used, :3], target[i], options.corner_radius * eyes)
        t, dist, bary, desc = cand[i]
        j = int(np.argmin(dist ** 2 + (desc[:, :3] @ u - (lo + frac * (hi - lo))) ** 2))
        W[i] = 0
        np.add.at(W[i], t[j], bary[j])
    return W


def find_landmarks(neutral, deltas, names, triangles, reference, scheme_name: str = "contours48",
                   options: FitOptions = FitOptions()) -> Derived:
    """The scheme's points found on a rig (:func:`find_ibug68`, then for contours48
    :func:`contours48_from_ibug68`, with the rig's eyeballs where it has some)."""
    W68 = find_ibug68(neutral, deltas, names, triangles, reference, options)
    width = eye_width(W68, np.asarray(neutral, np.float64))
    if scheme_name == "ibug68":
        return Derived(W68, [])
    d = contours48_from_ibug68(W68, np.asarray(neutral, np.float64), still_vertices(deltas, names, width))
    return d


def landmark_entries(W: np.ndarray) -> list:
    """A weight matrix's rows as landmark-file entries: a vertex index, or ``[[vertex, weight], ...]``."""
    out = []
    for row in np.asarray(W, np.float64):
        nz = np.flatnonzero(np.abs(row) > 1e-12)
        if len(nz) == 1:
            out.append(int(nz[0]))
        else:
            w = row[nz] / row[nz].sum()
            out.append([[int(v), float(x)] for v, x in zip(nz, w)])
    return out


#: the panels of the check sheet: caption, {shape name key: weight}
PANELS = (("neutral", {}), ("blink", {"eyeblinkleft": 1.0, "eyeblinkright": 1.0}), ("jaw open", {"jawopen": 1.0}),
          ("smile", {"mouthsmileleft": 1.0, "mouthsmileright": 1.0}))


def panel_curves(rig) -> tuple[list[str], np.ndarray]:
    """The :data:`PANELS` the rig has the shapes for: their captions and (n_panels, n_shapes) curves."""
    from keyshape.retarget.targets.target_set import name_key
    keys = [name_key(n) for n in rig.names]
    rows, captions = [], []
    for caption, mix in PANELS:
        c = np.zeros(rig.n_shapes)
        for k, w in mix.items():
            c[[j for j, x in enumerate(keys) if x == k]] = w
        if mix and not c.any():
            continue
        rows.append(c)
        captions.append(caption)
    return captions, np.stack(rows)
