"""dlib's generic 68-point landmarker (HOG face detector + ensemble-of-trees shape predictor).

An optional extra, ``pip install "keyshape[label]"`` (``dlib-bin`` and ``face-recognition-models``), imported
only when a :class:`DlibLandmarker` is made. Points in the iBUG-68 layout, image pixels, origin top-left. Of
several detections the one nearest the previous frame's face is kept when there is one, otherwise the largest.
A face reaching past the frame (a close-up) is found and read on the frame with a border (:func:`bordered`).
"""
from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keyshape.base.errors import KeyshapeError, MissingFileError

INSTALL_HINT = 'pip install "keyshape[label]"'
# iBUG-68 index of each point's mirror image (left-right flip of the face)
IBUG68_MIRROR = np.array(list(range(16, -1, -1)) + list(range(26, 16, -1)) + [27, 28, 29, 30] + [35, 34, 33, 32, 31]
                         + [45, 44, 43, 42, 47, 46, 39, 38, 37, 36, 41, 40]
                         + [54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55] + [64, 63, 62, 61, 60, 67, 66, 65])
# box moves (x, y as fractions of the box size, scale) of the averaged prediction
_BOX_MOVES = ((0.0, 0.0, 1.0), (0.04, 0.0, 1.0), (-0.04, 0.0, 1.0), (0.0, 0.04, 1.0), (0.0, -0.04, 1.0),
              (0.0, 0.0, 0.92), (0.0, 0.0, 1.08))
MODEL_NAME = "shape_predictor_68_face_landmarks.dat"
# the border a close-up's frame gets, a fraction of its larger side (docs/label.md, "Close-ups")
BORDER = 0.25


def _import_dlib():
    try:
        import dlib  # noqa: PLC0415 (optional dependency, imported lazily)
    except ImportError:
        raise KeyshapeError(f"the dlib landmarker needs dlib, which is not installed: "
                            f"{INSTALL_HINT}") from None
    return dlib


def default_model_path() -> Path:
    """Path of ``shape_predictor_68_face_landmarks.dat`` from ``face-recognition-models``.

    The package is located without importing it (its ``__init__`` needs
    ``pkg_resources``, absent from recent setuptools).
    """
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        raise KeyshapeError(f"the dlib landmarker needs face-recognition-models, which is not "
                            f"installed: {INSTALL_HINT}")
    path = Path(list(spec.submodule_search_locations)[0]) / "models" / MODEL_NAME
    if not path.is_file():
        raise MissingFileError(path, f"dlib shape model (reinstall with {INSTALL_HINT})")
    return path


@dataclass
class DlibLandmarker:
    """dlib HOG face detection followed by the 68-point shape predictor.

    Parameters
    ----------
    upsample : int
        Times the detector upsamples the image (finds smaller faces, slower).
    model_path : str or Path, optional
        A dlib shape predictor file; default: the one in ``face-recognition-models``.
    min_size : float
        Faces whose box is narrower than this many pixels are ignored.
    """

    upsample: int = 0
    model_path: str | Path | None = None
    min_size: float = 20.0

    def __post_init__(self):
        dlib = _import_dlib()
        path = Path(self.model_path) if self.model_path is not None else default_model_path()
        if not path.is_file():
            raise MissingFileError(path, "dlib shape model")
        self._dlib = dlib
        self._detector = dlib.get_frontal_face_detector()
        self._predictor = dlib.shape_predictor(str(path))

    @staticmethod
    def _gray(image: np.ndarray) -> np.ndarray:
        img = np.asarray(image)
        if img.ndim == 3:
            import cv2  # noqa: PLC0415
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        return np.ascontiguousarray(img, dtype=np.uint8)

    def detect_box(self, gray: np.ndarray, previous: np.ndarray | None = None):
        """The face box to use in ``gray`` (a ``dlib.rectangle``) or None.

        ``previous`` ((n_points, 2) points of the last frame) picks the detection
        nearest it; without it the largest detection is kept.
        """
        boxes = [b for b in self._detector(gray, self.upsample) if b.width() >= self.min_size]
        ok = previous is not None and np.all(np.isfinite(previous))
        return _pick(boxes, np.asarray(previous, dtype=np.float64).mean(axis=0) if ok else None)

    def predict(self, gray: np.ndarray, box) -> np.ndarray:
        """The (68, 2) float64 points of the face in ``box`` (a ``dlib.rectangle``)."""
        shape = self._predictor(gray, box)
        return np.array([(p.x, p.y) for p in shape.parts()], dtype=np.float64)

    def predict_averaged(self, gray: np.ndarray, box) -> np.ndarray:
        """The mean of the predictor's points over 14 views of the face: the box as found, moved by 4%
        of its size each way and scaled by 0.92 and 1.08, each also on the mirrored image (points mapped
        back by :data:`IBUG68_MIRROR`): the label pre-fill's points (docs/label.md, "Pre-fill").
        """
        gray = np.ascontiguousarray(gray)
        flipped = np.ascontiguousarray(gray[:, ::-1])
        w_img = gray.shape[1]
        rect = self._dlib.rectangle
        acc = np.zeros((68, 2))
        for dx, dy, sc in _BOX_MOVES:
            w, h = box.width(), box.height()
            cx = (box.left() + box.right()) / 2 + dx * w
            cy = (box.top() + box.bottom()) / 2 + dy * h
            hw, hh = w * sc / 2, h * sc / 2
            x0, y0, x1, y1 = (int(round(v)) for v in (cx - hw, cy - hh, cx + hw, cy + hh))
            acc += self.predict(gray, rect(x0, y0, x1, y1))
            m = self.predict(flipped, rect(w_img - 1 - x1, y0, w_img - 1 - x0, y1))[IBUG68_MIRROR]
            m[:, 0] = w_img - 1 - m[:, 0]
            acc += m
        return acc / (2 * len(_BOX_MOVES))

    def read_around(self, image: np.ndarray, points: np.ndarray, averaged: bool = False) -> np.ndarray | None:
        """The (68, 2) points of ``image`` (gray or BGR) read from a box around ``points`` (a nearby frame's) placed
        as the HOG detector places it (a centred box drifts down and shrinks), on the :func:`bordered` frame where
        it reaches past the frame. None where the points are not finite or the reading collapses."""
        points = np.asarray(points, np.float64)
        if not np.all(np.isfinite(points)):
            return None
        gray = self._gray(image)
        lo, hi = points.min(0), points.max(0)
        half = 0.49 * max(hi - lo)
        c = (lo + hi) / 2 - (0.0, 0.2 * half)
        x0, y0, x1, y1 = (int(round(v)) for v in (c[0] - half, c[1] - half, c[0] + half, c[1] + half))
        box, off = self._dlib.rectangle(x0, y0, x1, y1), 0
        if not inside(box, gray.shape):
            gray, off = bordered(gray)
            box = self._dlib.rectangle(x0 + off, y0 + off, x1 + off, y1 + off)
        pts = (self.predict_averaged(gray, box) if averaged else self.predict(gray, box)) - off
        lo, hi = pts.min(0), pts.max(0)
        return pts if np.all(np.isfinite(pts)) and min(hi - lo) >= self.min_size / 2 else None

    def detect(self, image: np.ndarray, previous: np.ndarray | None = None,
               averaged: bool = False) -> np.ndarray | None:
        """Detect a face in ``image`` (gray or BGR) and return its (68, 2) points, or None.

        ``averaged``: the points of :meth:`predict_averaged` (14 views) instead of one prediction.
        """
        gray, box, off = self.find(self._gray(image), previous)
        if box is None:
            return None
        return (self.predict_averaged(gray, box) if averaged else self.predict(gray, box)) - off

    def find(self, gray: np.ndarray, previous: np.ndarray | None = None) -> tuple[np.ndarray, object, int]:
        """``(image, box, offset)``: :meth:`detect_box`'s box in ``gray``, or where that box reaches past the frame
        or there is none, the box found in the :func:`bordered` frame, that frame and its border's width (box None
        where neither finds a face)."""
        box = self.detect_box(gray, previous)
        if box is None or not inside(box, gray.shape):
            big, p = bordered(gray)
            found = self.detect_box(big, None if previous is None else np.asarray(previous, np.float64) + p)
            if found is not None:
                return big, found, p
        return gray, box, 0


def inside(box, shape) -> bool:
    """Whether the ``dlib.rectangle`` ``box`` lies within an image of ``shape`` (rows, columns)."""
    return box.left() >= 0 and box.top() >= 0 and box.right() < shape[1] and box.bottom() < shape[0]


def bordered(gray: np.ndarray, border: float = BORDER) -> tuple[np.ndarray, int]:
    """``gray`` with a border of ``border`` times its larger side, in its mean grey, and the border's width: dlib's
    detector finds a face reaching past the frame whole only with room around it, and the shape predictor reads
    grey there rather than black (docs/label.md, "Close-ups")."""
    import cv2  # noqa: PLC0415

    p = int(round(border * max(gray.shape)))
    return cv2.copyMakeBorder(gray, p, p, p, p, cv2.BORDER_CONSTANT, value=int(round(cv2.mean(gray)[0]))), p


def _pick(boxes: list, centre: np.ndarray | None):
    """Of dlib's ``boxes``, the one nearest ``centre`` (x, y) where given, else the largest; None if none."""
    if not boxes:
        return None
    if centre is not None:
        return min(boxes, key=lambda b: (b.center().x - centre[0]) ** 2 + (b.center().y - centre[1]) ** 2)
    return max(boxes, key=lambda b: b.area())


def landmark_video_chained(path: str | Path, landmarker: DlibLandmarker | None = None, detect_every: int = 4,
                           progress=None, per_frame=None) -> np.ndarray:
    """dlib's points on every frame, cheaply: (n_frames, 68, 2), NaN where no face.

    The HOG detector runs every ``detect_every`` frames (and whenever the face was lost); in between, and where
    its box reaches past the frame, the shape predictor (about 2 ms) starts from a box around the previous
    frame's points (docs/label.md, "Which frames"; the frame bordered where that box reaches past it).
    ``per_frame(index, gray, points)`` is called for every frame with a face (extra cues from the pixels).
    """
    from keyshape.base.formats.video import VideoReader  # noqa: PLC0415

    lm = landmarker if landmarker is not None else DlibLandmarker()
    reader = VideoReader(path, gray=True)
    n = len(reader)
    out: list[np.ndarray] = []
    previous = None
    for i, gray in reader:
        gray = np.ascontiguousarray(gray, dtype=np.uint8)
        pts = None
        if previous is None:                     # a first face, a close-up's too: on the bordered frame if need be
            img, b, off = lm.find(gray)
            if b is not None:
                pts = lm.predict(img, b) - off
        elif i % max(1, int(detect_every)) == 0:
            b = lm.detect_box(gray, previous)
            if b is not None and inside(b, gray.shape):
                pts = lm.predict(gray, b)
        if pts is None and previous is not None:
            pts = lm.read_around(gray, previous)
        out.append(pts if pts is not None else np.full((68, 2), np.nan))
        if pts is not None and per_frame is not None:
            per_frame(i, gray, pts)
        previous = pts
        if progress is not None:
            progress(i + 1, n)
    return np.stack(out) if out else np.empty((0, 68, 2))
