"""Choose the frames worth labelling: few, varied, sharp, never near-duplicates.

With dlib's points (the default of ``keyshape label``) :func:`choose_frames_by_cues` chooses from expression and
pose cues, else :func:`choose_frames` from the frames' appearance; :func:`worst_explained` picks the frames a
first track explains worst (``--more``). The method: docs/label.md, "Which frames".
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from keyshape.base.errors import InputError

DESC_SIZE = 24


def face_crop(image: np.ndarray, box: tuple[int, int, int, int] | None) -> np.ndarray:
    """The ``box = (x0, y0, x1, y1)`` part of ``image``; default the central 60% x 80%."""
    h, w = image.shape[:2]
    if box is None:
        box = (int(0.2 * w), int(0.1 * h), int(0.8 * w), int(0.9 * h))
    x0, y0, x1, y1 = (int(v) for v in box)
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, w), min(y1, h)
    if x1 - x0 < 4 or y1 - y0 < 4:
        raise InputError(f"face box {box} leaves less than 4x4 pixels of a {w}x{h} frame")
    return image[y0:y1, x0:x1]


def describe(gray: np.ndarray, box=None) -> tuple[np.ndarray, float]:
    """Appearance descriptor (DESC_SIZE**2,) and sharpness (variance of Laplacian) of one frame."""
    import cv2  # noqa: PLC0415

    crop = face_crop(gray, box)
    small = cv2.resize(crop, (DESC_SIZE, DESC_SIZE), interpolation=cv2.INTER_AREA).astype(np.float32).ravel()
    small -= small.mean()
    small /= small.std() + 1e-6
    sharp = float(cv2.Laplacian(crop, cv2.CV_32F).var())
    return small, sharp


def describe_video(frames, box=None, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors (n_frames, DESC_SIZE**2) and sharpness (n_frames,) of an iterable of gray frames.

    ``frames`` yields ``(index, gray)`` pairs (a gray :class:`~keyshape.base.formats.video.VideoReader`).
    """
    desc, sharp = [], []
    for i, gray in frames:
        d, s = describe(gray, box)
        desc.append(d)
        sharp.append(s)
        if progress is not None:
            progress(i + 1)
    if not desc:
        raise InputError("no frames to choose from")
    return np.stack(desc), np.asarray(sharp)


@dataclass
class FrameChoice:
    """The chosen frames and why.

    Attributes
    ----------
    frames : (K,) int array, in time order
    cluster : (n_frames,) int array
        Micro-cluster of every frame (-1: dropped as too small).
    features : (n_frames, n_components) array
        The PCA features the choice was made in.
    sharpness : (n_frames,) array
    """

    frames: np.ndarray
    cluster: np.ndarray
    features: np.ndarray
    sharpness: np.ndarray


def choose_frames(descriptors: np.ndarray, sharpness: np.ndarray, count: int, *, min_gap: int = 12,
                  sharp_window: int = 4, min_cluster: int = 3, n_components: int = 16,
                  exclude=(), rng=None) -> FrameChoice:
    """Pick ``count`` varied, sharp frames from per-frame descriptors (see module docstring).

    Parameters
    ----------
    descriptors : (n_frames, d) array
    sharpness : (n_frames,) array
        Larger is sharper (variance of Laplacian).
    count : int
        Frames to choose (K).
    min_gap : int
        No two chosen frames (nor a chosen and an ``exclude``d one) closer than this in time.
    sharp_window : int
        A chosen frame may move this many frames to a sharper neighbour of its cluster.
    min_cluster : int
        Micro-clusters with fewer frames are ignored (glitches, cuts).
    n_components : int
        PCA dimensions of the features.
    exclude : iterable of int
        Frames not to choose (and to keep ``min_gap`` away from), e.g. already labelled ones.
    rng : None, int or numpy.random.Generator
        Seeds k-means.
    """
    from sklearn.cluster import KMeans  # noqa: PLC0415
    from sklearn.decomposition import PCA  # noqa: PLC0415

    X = np.asarray(descriptors, dtype=np.float64)
    sharp = np.asarray(sharpness, dtype=np.float64)
    n = len(X)
    if X.ndim != 2 or len(sharp) != n:
        raise InputError(f"descriptors (n_frames, d) and sharpness (n_frames,) disagree: "
                         f"{X.shape} vs {sharp.shape}")
    count = int(count)
    if count < 1:
        raise InputError(f"--count must be at least 1, got {count}")
    excluded = np.array(sorted(set(int(i) for i in exclude)), dtype=np.intp)
    free = np.ones(n, bool)
    for e in excluded:
        free[max(e - min_gap + 1, 0):e + min_gap] = False
    if count > free.sum():
        raise InputError(f"cannot choose {count} frames from a video of {n} frames "
                         f"({int(free.sum())} free after exclusions)")
    seed = np.random.default_rng(rng).integers(2**31 - 1)
    k_comp = max(1, min(n_components, n - 1, X.shape[1]))
    F = PCA(n_components=k_comp, random_state=int(seed)).fit_transform(X) if n > 1 else X[:, :1] * 0
    n_distinct = len(np.unique(np.round(F, 6), axis=0))  # a still video repeats frames exactly
    n_micro = int(min(max(4 * count, count + 1), n_distinct))
    km = KMeans(n_clusters=n_micro, n_init=2, random_state=int(seed)).fit(F)
    labels = km.labels_.copy()
    sizes = np.bincount(labels, minlength=n_micro)
    small = sizes < min(min_cluster, max(1, n // (4 * n_micro)))
    labels[small[labels]] = -1
    # medoid of each kept micro-cluster (member nearest its centroid), free frames only
    d_cent = np.linalg.norm(F - km.cluster_centers_[km.labels_], axis=1)
    cand = []
    for c in np.flatnonzero(~small):
        members = np.flatnonzero((labels == c) & free)
        if len(members):
            cand.append(members[np.argmin(d_cent[members])])
    cand = np.array(cand, dtype=np.intp)
    if len(cand) < count:  # too few clusters survive: fall back to every free frame
        cand = np.flatnonzero(free)
    # farthest-point sampling, starting nearest the mean appearance
    chosen: list[int] = []
    dist = np.full(len(cand), np.inf)
    blocked = np.zeros(len(cand), bool)
    nxt = int(np.argmin(np.linalg.norm(F[cand] - F.mean(axis=0), axis=1)))
    while len(chosen) < count:
        f = int(cand[nxt])
        chosen.append(f)
        blocked |= np.abs(cand - f) < min_gap
        dist = np.minimum(dist, np.linalg.norm(F[cand] - F[f], axis=1))
        score = np.where(blocked, -np.inf, dist)
        if len(chosen) < count:
            if not np.isfinite(score.max()):  # candidates exhausted: widen to every free frame
                rest = np.flatnonzero(free)
                far = np.min(np.abs(rest[:, None] - np.array(chosen)[None]), axis=1) >= min_gap
                if not far.any():
                    raise InputError(f"cannot choose {count} frames at least {min_gap} frames apart "
                                     f"from a video of {n} frames")
                cand = rest[far]
                dist = np.min(np.linalg.norm(F[cand][:, None] - F[chosen][None], axis=2), axis=1)
                blocked = np.zeros(len(cand), bool)
                score = dist
            nxt = int(np.argmax(score))
    # swap each for the sharpest temporal neighbour that still looks more like it than like any
    # other chosen frame (motion blur changes the descriptor a little, a new expression a lot)
    chosen_arr = np.array(chosen)
    final = []
    for f in chosen:
        nb = np.arange(max(f - sharp_window, 0), min(f + sharp_window + 1, n))
        nb = nb[free[nb]]
        others = chosen_arr[chosen_arr != f]
        if len(others):
            d_self = np.linalg.norm(F[nb] - F[f], axis=1)
            d_other = np.min(np.linalg.norm(F[nb][:, None] - F[others][None], axis=2), axis=1)
            nb = nb[d_self < 0.5 * d_other]
        if final:
            nb = nb[np.min(np.abs(nb[:, None] - np.array(final)[None]), axis=1) >= min_gap]
        final.append(int(nb[np.argmax(sharp[nb])]) if len(nb) else f)
    return FrameChoice(np.array(sorted(final), dtype=np.intp), labels, F, sharp)


# ----------------------------------------------------------------------------- shape cues (dlib pre-fill)

def _face_frame(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """iBUG-68 shapes (n, 68, 2) in a face frame (origin between the outer eye corners, x along the eye line,
    inter-ocular units), and the eye line's angle (n,) (radians)."""
    eye = p[:, 45] - p[:, 36]
    iod = np.linalg.norm(eye, axis=1)
    ang = np.arctan2(eye[:, 1], eye[:, 0])
    c, s = np.cos(-ang), np.sin(-ang)
    d = p - ((p[:, 36] + p[:, 45]) / 2)[:, None]
    q = np.stack([c[:, None] * d[..., 0] - s[:, None] * d[..., 1],
                  s[:, None] * d[..., 0] + c[:, None] * d[..., 1]], -1) / iod[:, None, None]
    return q, ang


def shape_cues(points68: np.ndarray) -> np.ndarray:
    """Per-frame expression and pose cues of iBUG-68 shapes ``(n, 68, 2)`` -> ``(n, 7)``.

    Distances are in inter-ocular units (outer eye corners) in a face frame
    rotated by the eye line: eye aperture (mean lid gap of both eyes), inner-lip
    gap, mouth width, brow height above the eye centres, yaw (nose tip's
    horizontal offset from the eyes' midpoint), pitch (nose tip's drop below
    the eye line over the chin's), roll (eye-line angle, radians). NaN rows
    stay NaN.
    """
    q, ang = _face_frame(np.asarray(points68, np.float64))

    def gap(a, b):
        return np.linalg.norm(q[:, a] - q[:, b], axis=-1)

    eye_ap = (gap(37, 41) + gap(38, 40) + gap(43, 47) + gap(44, 46)) / 4
    mouth_ap = gap(62, 66)
    width = gap(48, 54)
    eye_y = q[:, 36:48, 1].mean(1)
    brow = eye_y - q[:, 17:27, 1].mean(1)
    yaw = q[:, 30, 0]
    pitch = q[:, 30, 1] / np.maximum(q[:, 8, 1], 1e-6)
    return np.stack([eye_ap, mouth_ap, width, brow, yaw, pitch, ang], 1)


def eye_profile(gray: np.ndarray, points68: np.ndarray, width: int = 16, height: int = 10) -> np.ndarray:
    """Vertical intensity profile of both eyes ``(2 * height,)``: a cheap eye-closure cue from the pixels.

    Each eye's box (between its corners, as tall as half their distance, turned
    with them) is sampled at ``width`` x ``height`` and averaged along the
    rows; the profile is normalised to zero mean and unit variance. An open
    eye has a dark band (iris, lashes) that a closed lid replaces by skin;
    averaging along the rows makes it insensitive to where the eye looks.
    dlib's lid points are not needed, only its eye corners (which it finds
    far more reliably than the lids).
    """
    import cv2  # noqa: PLC0415

    out = []
    for a, b in ((36, 39), (42, 45)):
        p, q = np.asarray(points68[a], np.float64), np.asarray(points68[b], np.float64)
        u = (q - p) / width                         # model x step in image pixels
        v = np.array([-u[1], u[0]]) * (0.5 * width / height)
        origin = p - v * (height / 2)
        m = np.array([[u[0], v[0], origin[0]], [u[1], v[1], origin[1]]])
        patch = cv2.warpAffine(gray, m, (width, height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
        out.append(patch.mean(1))
    prof = np.concatenate(out)
    prof -= prof.mean()
    return prof / (prof.std() + 1e-6)


def choose_frames_by_cues(points68: np.ndarray, count: int, *, min_gap: int = 12, exclude=(),
                          n_blinks: int | None = None, blink_ratio: float = 0.7, eye_profiles: np.ndarray | None = None,
                          extreme_tol: float = 0.15) -> np.ndarray:
    """Choose ``count`` frames covering the performance from per-frame iBUG-68 shapes (dlib over the video).

    Farthest-point sampling over robust z-scores of :func:`shape_cues` and the face-frame shapes' first
    principal components, then the deepest blinks (``n_blinks``, default ``max(1, count // 5)``; eye aperture
    below ``blink_ratio`` of its median, or with ``eye_profiles`` from :func:`eye_profile` a profile far from the
    median open eye) and, with ``count`` >= 6, the mouth's extremes (when no chosen frame is within
    ``extreme_tol`` of the cue's range of them) replace the most redundant chosen frames. Frames without a face
    are never chosen.
    The method: docs/label.md, "Which frames". Returns the chosen frame indices in time order.
    """
    p = np.asarray(points68, np.float64)
    n = len(p)
    count = int(count)
    if count < 1:
        raise InputError(f"--count must be at least 1, got {count}")
    ok = np.isfinite(p).all(axis=(1, 2))
    free = ok.copy()
    for e in set(int(i) for i in exclude):
        free[max(e - min_gap + 1, 0):e + min_gap] = False
    if free.sum() < count:
        raise InputError(f"cannot choose {count} frames: the pre-fill found a face in only {int(free.sum())} "
                         f"free frames of {n}")
    cues = shape_cues(np.where(ok[:, None, None], p, 0.0) + np.where(ok[:, None, None], 0.0, np.nan))
    cv = cues[ok]
    med = np.median(cv, 0)
    iqr = np.subtract(*np.percentile(cv, [75, 25], 0)) / 1.35
    # at least an eighth of the 1-99% range: a mouth closed most of the time has a tiny IQR
    span = np.subtract(*np.percentile(cv, [99, 1], 0))
    scale = np.maximum(np.maximum(iqr, span / 8.0), 1e-6)
    z = np.clip((cues - med) / scale, -8, 8)
    z[:, 0] *= 2.0
    z[:, 1] *= 2.0
    # face-frame shapes (cues' normalisation) -> PCA, scaled so the first component has unit spread
    q, _ = _face_frame(p)
    flat = q[:, 17:].reshape(n, -1)
    mu = flat[ok].mean(0)
    _, sv, vt = np.linalg.svd(flat[ok] - mu, full_matrices=False)
    k = min(8, len(sv))
    shp = np.zeros((n, k))
    shp[ok] = (flat[ok] - mu) @ vt[:k].T / max(sv[0] / np.sqrt(ok.sum()), 1e-9)
    X = np.hstack([z, np.clip(shp, -6, 6)])
    X[~ok] = 0.0
    cand = np.flatnonzero(free)
    chosen: list[int] = [int(cand[np.argmin(np.linalg.norm(X[cand] - np.median(X[cand], 0), axis=1))])]
    dist = np.linalg.norm(X[cand] - X[chosen[0]], axis=1)
    blocked = np.abs(cand - chosen[0]) < min_gap
    while len(chosen) < count:
        score = np.where(blocked, -np.inf, dist)
        if not np.isfinite(score.max()):
            raise InputError(f"cannot choose {count} frames at least {min_gap} frames apart from {n} frames")
        f = int(cand[np.argmax(score)])
        chosen.append(f)
        blocked |= np.abs(cand - f) < min_gap
        dist = np.minimum(dist, np.linalg.norm(X[cand] - X[f], axis=1))
    # blinks: make sure some chosen frames have the eyes closed
    n_blinks = max(1, count // 5) if n_blinks is None else int(n_blinks)
    eye_ap = cues[:, 0]
    is_blink = free & (eye_ap < blink_ratio * med[0])
    depth = -eye_ap
    if eye_profiles is not None:
        prof = np.asarray(eye_profiles, np.float64)
        okp = ok & np.isfinite(prof).all(1)
        dist = np.full(n, -np.inf)
        dist[okp] = np.linalg.norm(prof[okp] - np.median(prof[okp], 0), axis=1)
        dmed = np.median(dist[okp])
        dmad = np.median(np.abs(dist[okp] - dmed)) / 0.6745 + 1e-9
        zd = (dist - dmed) / dmad
        is_blink = free & (zd > 3.0) & (eye_ap < med[0])
        depth = np.where(okp, zd, -np.inf)
    have = [f for f in chosen if is_blink[f]]
    protected = set(have)

    def swap_in(b: int) -> bool | None:
        """Put frame ``b`` among the chosen (protected); False: not possible here, None: nothing left to swap."""
        near = [j for j, f in enumerate(chosen) if abs(int(b) - f) < min_gap]
        if len(near) > 1 or any(chosen[j] in protected for j in near):
            return False
        if near:        # a chosen frame next to it gives way to it
            j = near[0]
        else:           # else the most redundant chosen frame (nearest to another chosen one)
            cs = np.array(chosen)
            dd = np.linalg.norm(X[cs][:, None] - X[cs][None], axis=2)
            np.fill_diagonal(dd, np.inf)
            js = [j for j in np.argsort(dd.min(1)) if chosen[j] not in protected]
            if not js:
                return None
            j = int(js[0])
        chosen[j] = int(b)
        protected.add(int(b))
        return True

    if is_blink.any() and len(have) < n_blinks and count > 1:
        order = np.flatnonzero(is_blink)
        order = order[np.argsort(-depth[order])]
        for b in order:
            if len(have) >= n_blinks:
                break
            done = swap_in(int(b))
            if done is None:
                break
            if done:
                have.append(int(b))
    # mouth extremes: the widest-open mouth, the widest (smile) and the narrowest (pucker) mouth
    if count >= 6:
        from scipy.ndimage import median_filter  # noqa: PLC0415

        for col, sign in ((1, 1.0), (2, 1.0), (2, -1.0)):
            v = np.where(ok, cues[:, col], np.nan)
            # a 5-frame running median: one frame of dlib glitch is not an extreme
            vm = median_filter(np.nan_to_num(v, nan=float(med[col])), size=5, mode="nearest") * sign
            vm[~free] = -np.inf
            lo, hi = np.percentile(cv[:, col] * sign, [1, 100])
            if not np.isfinite(vm).any() or hi - lo <= 1e-9:
                continue
            best = float(np.max(vm[chosen]))
            if best >= vm.max() - extreme_tol * (hi - lo):
                continue
            for b in np.argsort(-vm)[:4 * min_gap]:
                if vm[b] < best or not np.isfinite(vm[b]):
                    break
                done = swap_in(int(b))
                if done is not False:
                    break
    return np.array(sorted(chosen), dtype=np.intp)


def worst_explained(confidence: np.ndarray, success: np.ndarray, count: int, exclude=(), min_gap: int = 12,
                    frames: np.ndarray | None = None) -> np.ndarray:
    """Active labelling: the ``count`` frames a first track explains worst, ``min_gap`` apart and from ``exclude``.

    Lost frames (``success`` False) come first, then the lowest confidence
    (the appearance residual of :class:`~keyshape.tracker.fitting.Tracker`).
    Each pick blocks ``min_gap`` frames either side, so one hard stretch (a
    laugh, a head turn) gives one frame, the next worst stretch the next.
    ``frames`` are the video frame numbers of the rows (default 0..n-1).
    """
    conf = np.asarray(confidence, np.float64)
    ok = np.asarray(success, bool)
    idx = np.arange(len(conf)) if frames is None else np.asarray(frames, np.intp)
    score = np.where(ok, 1.0 - np.nan_to_num(conf, nan=0.0), 2.0)
    free = np.ones(len(conf), bool)
    ex = np.array(sorted(set(int(e) for e in exclude)), np.intp)
    if len(ex):
        free &= np.min(np.abs(idx[:, None] - ex[None]), axis=1) >= min_gap
    out: list[int] = []
    while len(out) < int(count):
        cand = np.flatnonzero(free)
        if not len(cand):
            break
        j = int(cand[np.argmax(score[cand])])
        out.append(int(idx[j]))
        free &= np.abs(idx - idx[j]) >= min_gap
    return np.array(sorted(out), np.intp)
