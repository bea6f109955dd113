"""Synthetic camcorder footage of a talking face with exact ground truth: the public API.

Design notes and figures: docs/synth.md, "Notes on the code", ``data_synth/video.py``.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from keyshape.data_synth.face_model import COMPONENTS, FaceModel
from keyshape.data_synth.performance import make_performance
from keyshape.data_synth.render import FaceRenderer
from keyshape.base.errors import InputError
from keyshape.base.files import atomic_dir, atomic_path, atomic_write
from keyshape.base.progress import Progress
from keyshape.base.formats.tracks import Tracks, write_tracks
from keyshape.base.formats.labels import footage_record, write_footage, write_labels
from keyshape.base.formats.video import video_writer

#: Fraction of the frame interval the shutter is open (sets the motion blur length).
SHUTTER = 0.6
#: Model point whose image motion sets the motion blur (between the eyes and the mouth).
_BLUR_POINT = np.array([0.0, 20.0])


def _check_args(frames, seed, size, fps, labels=None) -> tuple[int, int, tuple[int, int], float]:
    try:
        frames_i = int(frames)
    except (TypeError, ValueError):
        raise InputError(f"frames: expected a whole number, got {frames!r}") from None
    if frames_i != frames or frames_i <= 0:
        raise InputError(f"frames: expected a positive whole number, got {frames!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed: expected a non-negative integer, got {seed!r}")
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise InputError(f"size: expected (width, height), got {size!r}") from None
    if w < 96 or h < 72 or w > 8192 or h > 8192:
        raise InputError(f"size: expected width >= 96 and height >= 72 pixels (at most 8192), got {w}x{h}")
    try:
        fps_f = float(fps)
    except (TypeError, ValueError):
        raise InputError(f"fps: expected a number, got {fps!r}") from None
    if not np.isfinite(fps_f) or fps_f <= 0:
        raise InputError(f"fps: expected a positive frame rate, got {fps!r}")
    if labels is not None:
        if isinstance(labels, bool) or not isinstance(labels, (int, np.integer)) or labels < 1:
            raise InputError(f"labels: expected a positive whole number of label frames, got {labels!r}")
        if labels > frames_i:
            raise InputError(f"labels: cannot suggest {labels} label frames from a video of {frames_i} frames")
    return frames_i, int(seed), (w, h), fps_f


def parse_size(text: str) -> tuple[int, int]:
    """Parse ``"WxH"`` (e.g. ``640x480``) into ``(width, height)``; raise :class:`InputError` otherwise."""
    parts = str(text).lower().replace("*", "x").split("x")
    try:
        if len(parts) != 2:
            raise ValueError
        w, h = int(parts[0]), int(parts[1])
    except ValueError:
        raise InputError(f"size: expected WIDTHxHEIGHT such as 640x480, got {text!r}") from None
    return w, h


class SyntheticVideo:
    """A synthetic talking-face performance: the hidden truth, and frames rendered on demand.

    Parameters
    ----------
    frames : int
        Number of frames.
    seed : int
        Fixes everything: face proportions and look, performance, noise.
    size : (width, height)
    fps : float

    Attributes
    ----------
    model : FaceModel
    performance : Performance
    renderer : FaceRenderer
    pose : (n_frames, 2, 3) ``image_from_model`` per frame.
    model_points : (n_frames, 48, 2) ``contours48`` landmarks in the model frame.
    points : (n_frames, 48, 2) ``contours48`` landmarks in image pixels.

    Notes
    -----
    :meth:`frame` depends only on ``(seed, index)``: the sensor noise of frame
    ``t`` comes from its own generator ``default_rng([seed, 1, t])``, so any
    frame can be rendered alone and two renders are identical.
    """

    def __init__(self, frames: int = 600, seed: int = 0, size=(640, 480), fps: float = 30.0):
        frames, seed, size, fps = _check_args(frames, seed, size, fps)
        self.seed, self.size, self.fps = seed, size, fps
        r_model, r_perf, r_look = np.random.default_rng([seed, 0]).spawn(3)
        self.model = FaceModel(r_model)
        self.performance = make_performance(frames, fps, r_perf)
        self.renderer = FaceRenderer(self.model, size, r_look)
        self.pose = self.renderer.poses(self.performance)
        self.curves = self.model.curves(self.performance.weights, self.performance.gaze)
        self.model_points = self.model.landmarks(self.performance.weights, self.performance.gaze, curves=self.curves)
        self.points = np.einsum("nij,npj->npi", self.pose[:, :, :2], self.model_points) + self.pose[:, None, :, 2]

    @property
    def n_frames(self) -> int:
        return self.performance.n_frames

    @property
    def weights(self) -> np.ndarray:
        """Hidden expression weights ``(n_frames, n_components)``, columns named by :data:`COMPONENTS`."""
        return self.performance.weights

    def motion(self, t: int) -> np.ndarray:
        """Image motion (pixels) of the face centre during frame ``t``'s exposure."""
        n = self.n_frames
        a, b = self.pose[max(t - 1, 0)], self.pose[min(t + 1, n - 1)]
        span = max(min(t + 1, n - 1) - max(t - 1, 0), 1)
        v = (b[:, :2] @ _BLUR_POINT + b[:, 2] - a[:, :2] @ _BLUR_POINT - a[:, 2]) / span
        return SHUTTER * v

    def frame(self, t: int) -> np.ndarray:
        """Render frame ``t`` (BGR uint8, ``(height, width, 3)``), before video encoding."""
        t = int(t)
        if not 0 <= t < self.n_frames:
            raise InputError(f"frame {t} is outside 0..{self.n_frames - 1}")
        perf = self.performance
        c = {k: v[t] for k, v in self.curves.items()}
        canvas, alpha = self.renderer.render_canvas(c, perf.weights[t], perf.light[t])
        rng = np.random.default_rng([self.seed, 1, t])
        return self.renderer.composite(canvas, alpha, self.pose[t], self.renderer.model_scale * perf.shift[t],
                                       perf.exposure[t], self.motion(t), rng)

    def tracks(self) -> Tracks:
        """The ground truth as :class:`~keyshape.base.formats.tracks.Tracks` (confidence 1, success everywhere)."""
        n = self.n_frames
        return Tracks(np.arange(n), np.arange(n) / self.fps, np.ones(n), np.ones(n, bool), self.points, self.pose)

    def truth(self) -> dict:
        """The hidden truth as a JSON-ready dict (the layout of ``truth.json``, see ``docs/synth.md``)."""
        neutral, basis = self.model.basis()
        perf = self.performance
        r = lambda a, d=5: np.round(np.asarray(a, dtype=np.float64), d).tolist()  # noqa: E731
        return {
            "format": "keyshape-synth-truth/1",
            "seed": self.seed, "size": list(self.size), "fps": self.fps, "n_frames": self.n_frames,
            "scheme": "contours48",
            "components": list(COMPONENTS),
            "side_convention": "_L/_R are the subject's left/right; the subject's left is image-right "
                               "(eyeBlink_L closes the image-right eye, points 18-25)",
            "model_frame": "x to the image-right, y down, about one 640x480 pixel per unit; "
                           "image = pose[:, :2] @ model + pose[:, 2] with pose from truth.csv",
            "weights": r(perf.weights),
            "gaze": r(perf.gaze),
            "neutral": r(neutral, 4),
            "basis": r(basis, 4),
            "linear_residual": round(self.model.linear_residual(perf.weights), 4),
            "model_points": r(self.model_points, 4),
            "head": {"roll_deg": r(perf.roll_deg, 4), "scale": r(perf.scale), "shift": r(perf.shift, 4)},
            "light": r(perf.light, 4),
            "exposure": r(perf.exposure),
        }

    def label_frames(self, k: int) -> np.ndarray:
        """``k`` frames that span the performance, sorted (see :func:`select_label_frames`)."""
        perf = self.performance
        feats = np.column_stack([perf.weights, 0.5 * perf.gaze, 0.5 * perf.roll_deg / 15.0,
                                 0.5 * (perf.scale - 1) / 0.1, 0.5 * perf.shift / [30.0, 15.0]])
        return select_label_frames(feats, k, n_weights=len(COMPONENTS))


def select_label_frames(features: np.ndarray, k: int, n_weights: int | None = None) -> np.ndarray:
    """Label frames that span a performance: the most neutral frame, each weight's extreme, then farthest points.

    Parameters
    ----------
    features : (n_frames, n_features) per-frame description; the first
        ``n_weights`` columns are expression weights (the rest, e.g. gaze and
        head pose, only take part in the farthest-point fill).
    k : int, 1 <= k <= n_frames.
    n_weights : int, optional
        Number of leading weight columns (default: all columns).

    Returns
    -------
    (k,) sorted distinct frame indices. The first pick is the frame with the
    smallest weights; then, strongest first, the frame where each weight peaks
    (skipped when it repeats a chosen frame); then farthest-point sampling:
    each new pick maximises its distance to the frames already chosen, so the
    set has no near-duplicates while distinct frames remain.
    """
    f = np.asarray(features, dtype=np.float64)
    nw = f.shape[1] if n_weights is None else int(n_weights)
    w = f[:, :nw]
    chosen = [int(np.argmin(np.linalg.norm(w, axis=1)))]
    for j in np.argsort(-w.max(axis=0), kind="stable"):          # loop over weights, not frames
        if len(chosen) >= k or w[:, j].max() <= 0:
            break
        i = int(np.argmax(w[:, j]))
        if np.linalg.norm(f[chosen] - f[i], axis=1).min() > 1e-9:
            chosen.append(i)
    d = np.min(np.linalg.norm(f[:, None, :] - f[None, chosen, :], axis=2), axis=1)
    d[chosen] = -1.0
    while len(chosen) < k:      # loop over labels, not frames
        j = int(np.argmax(d))
        chosen.append(j)
        d = np.minimum(d, np.linalg.norm(f - f[j], axis=1))
        d[chosen] = -1.0
    return np.array(sorted(chosen), dtype=np.intp)


def synthesize(out_dir, frames: int = 600, seed: int = 0, size=(640, 480), fps: float = 30.0, labels: int = 12,
               preview=None, verbose: bool = False) -> dict[str, Path]:
    """Write synthetic camcorder footage of a talking face and its exact ground truth.

    Parameters
    ----------
    out_dir : str or Path
        Output folder (created).
    frames : int
        Number of frames (default 600).
    seed : int
        Same seed, same truth and same frames before encoding.
    size : (width, height)
        Frame size in pixels (default 640x480).
    fps : float
    labels : int
        Number of suggested training frames written to ``labels/``.
    preview : str or Path, optional
        Write a contact sheet PNG of 12 frames across the video with the ground truth drawn.
    verbose : bool
        Report progress on standard error.

    Returns
    -------
    dict with paths ``video``, ``truth`` (tracks CSV), ``labels`` (folder),
    ``truth_json`` and, when asked, ``preview``.
    """
    frames, seed, size, fps = _check_args(frames, seed, size, fps, labels)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sv = SyntheticVideo(frames, seed, size, fps)
    paths = {"video": out / "video.mp4", "truth": out / "truth.csv", "labels": out / "labels",
             "truth_json": out / "truth.json"}
    kept = render_video(paths["video"], sv.frame, frames, fps, size, preview, "synth video", verbose)
    write_truth(paths, sv, labels, preview, kept, write_preview)
    return paths


def render_video(path, frame, frames: int, fps: float, size, preview: bool, desc: str,
                 verbose: bool) -> dict[int, np.ndarray]:
    """Encode ``frame(t)`` for ``t`` in ``0 .. frames - 1`` into the video ``path``, with a progress bar
    ``desc``; returns the frames kept for the contact sheet (12 spread over the take; none without
    ``preview``). Shared by the synthetic generators (``synth video``, ``synth face3d``)."""
    n_sheet = min(12, frames)
    sheet_idx = set(np.linspace(0, frames - 1, n_sheet).round().astype(int).tolist()) if preview else set()
    kept: dict[int, np.ndarray] = {}
    with video_writer(path, fps, size) as writer, Progress(frames, desc, enabled=verbose) as prog:
        for t in range(frames):
            img = frame(t)
            writer.write(img)
            if t in sheet_idx:
                kept[t] = img
            prog.update()
    return kept


def write_truth(paths: dict, sv, labels: int, preview, kept: dict, preview_writer) -> None:
    """What every synthetic take writes beside its video: the truth tracks, ``labels`` training frames
    (``labels/``), ``truth.json`` and, with ``preview``, a contact sheet of the ``kept`` frames
    (``preview_writer(path, sv, kept)``). ``sv`` has ``tracks()``, ``label_frames(n)``, ``points`` and ``truth()``."""
    write_tracks(paths["truth"], sv.tracks())
    with atomic_dir(paths["labels"], kind="synth labels") as tmp:
        idx = sv.label_frames(labels)
        write_labels(tmp, idx, sv.points[idx])
        write_footage(tmp, footage_record(paths["video"]))
    with atomic_write(paths["truth_json"]) as f:
        json.dump(sv.truth(), f, separators=(",", ":"))
    if preview:
        paths["preview"] = preview_writer(preview, sv, kept)


def write_preview(path, sv: SyntheticVideo, frames: dict[int, np.ndarray], tile_width: int = 400,
                  caption=None) -> Path:
    """Contact sheet of ``frames`` (index -> image) as face close-ups with the ground truth drawn, as a PNG.

    Each tile is the face region of a frame, enlarged to ``tile_width`` pixels
    before the contours are drawn so that a person can check that they follow
    the lids, lips, brows and pupils; the caption names the frame and its
    strongest hidden weights (or ``caption(t)``: the 3D take's head angles).
    """
    from keyshape.base.draw import contact_sheet, crop_around, draw_shape
    from keyshape.base.schemes import load_scheme

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise InputError("preview must be a .png file", path)
    scheme = load_scheme("contours48")
    tiles, caps = [], []
    for t in sorted(frames):
        crop, pts = crop_around(frames[t], sv.points[t], margin=0.3)
        f = tile_width / crop.shape[1]
        big = cv2.resize(crop, (tile_width, int(round(crop.shape[0] * f))), interpolation=cv2.INTER_CUBIC)
        tiles.append(draw_shape(big, pts * f + (f - 1) / 2, scheme))
        caps.append(caption(t) if caption is not None else _weights_caption(sv, t))
    sheet = contact_sheet(tiles, caps, columns=4, tile_width=tile_width)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), sheet):
            raise InputError("cannot write the preview image", path)
    return path


def _weights_caption(sv: SyntheticVideo, t: int) -> str:
    top = np.argsort(-sv.weights[t])[:2]
    return f"frame {t}: " + ", ".join(f"{COMPONENTS[j]} {sv.weights[t, j]:.2f}" for j in top
                                      if sv.weights[t, j] >= 0.05)
