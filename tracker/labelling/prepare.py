"""Make a label folder: choose frames, save them as images, pre-fill their points, draw a contact sheet.

The I/O side of ``keyshape label``. Running it again on the same folder and video keeps the chosen frames and any
``.pts`` file already there (the user's corrections), and only redraws the contact sheet.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.files import atomic_write
from keyshape.base.formats.labels import SESSION_FILE

MEAN_SHAPE = Path(__file__).parent / "ibug68_mean.json"


def mean_ibug68() -> np.ndarray:
    """Mean iBUG-68 shape (68, 2): origin between the outer eye corners, unit corner distance."""
    return np.asarray(json.loads(MEAN_SHAPE.read_text())["points"], dtype=np.float64)


def template_points(scheme, width: int, height: int) -> np.ndarray:
    """A generic face in ``scheme``'s layout, centred in a ``width`` x ``height`` frame (no pre-fill)."""
    p = mean_ibug68() * (0.3 * min(width, height)) + [width / 2, 0.4 * height]
    return _from_ibug68(p, scheme, None, f"no starting template for scheme {scheme.name!r} ({scheme.n_points} "
                        "points): use contours48 or ibug68")


def _from_ibug68(p: np.ndarray, scheme, image, refusal: str) -> np.ndarray:
    """iBUG-68 points ``p`` in ``scheme``'s layout (``image``: the frame, for the pupils); ``refusal``
    is the error for a scheme other than ibug68 or contours48."""
    from keyshape.tracker.labelling.convert import ibug68_to_contours48  # noqa: PLC0415

    if scheme.core == 68:
        return with_auxiliary(p, p, scheme)
    if scheme.core == 48:
        return with_auxiliary(ibug68_to_contours48(p, image), p, scheme)
    raise InputError(refusal)


def with_auxiliary(points: np.ndarray, points68: np.ndarray, scheme) -> np.ndarray:
    """``points`` (the base scheme's) followed by the auxiliary points of a :meth:`~keyshape.base.schemes.Scheme.full`
    ``scheme``, taken at their iBUG-68 sources in ``points68``."""
    if not scheme.n_core:
        return points
    return np.concatenate([points, points68[scheme.auxiliary_sources]])


def face_box(frames: np.ndarray, landmarker, margin: float = 0.15) -> tuple[int, int, int, int] | None:
    """Box around every face dlib finds in ``frames`` (gray), enlarged by ``margin``; None if none."""
    boxes = []
    for g in frames:
        pts = landmarker.detect(g)
        if pts is not None:
            boxes.append(np.r_[pts.min(axis=0), pts.max(axis=0)])
    if not boxes:
        return None
    b = np.asarray(boxes)
    lo, hi = np.median(b[:, :2], axis=0), np.median(b[:, 2:], axis=0)
    pad = margin * (hi - lo)
    lo, hi = lo - pad, hi + pad
    h, w = frames[0].shape[:2]
    return (int(max(lo[0], 0)), int(max(lo[1], 0)), int(min(hi[0], w)), int(min(hi[1], h)))


def prefill(images: np.ndarray, scheme, landmarker, near: np.ndarray | None = None) -> list[np.ndarray | None]:
    """dlib's points for each image (BGR) in ``scheme``'s layout; None where no face is found.

    Each face's points are the mean over 14 views (:meth:`DlibLandmarker.predict_averaged`). ``near`` ((n, 68, 2),
    NaN where unknown): dlib's points of the same frames from the whole-video pass
    (:func:`~keyshape.tracker.labelling.dlib_landmarker.landmark_video_chained`), which pick the detection and,
    where the detector finds no face (a close-up, a turned head), place the box
    (:meth:`DlibLandmarker.read_around`).
    """
    out: list[np.ndarray | None] = []
    for k, im in enumerate(images):
        hint = None if near is None or not np.isfinite(near[k]).all() else near[k]
        p = landmarker.detect(im, previous=hint, averaged=True)
        if p is None and hint is not None:
            p = landmarker.read_around(im, hint, averaged=True)
        out.append(None if p is None else _from_ibug68(
            p, scheme, im, f"dlib pre-fill gives ibug68 or contours48, not {scheme.name!r}: use --no-prefill"))
    return out


def write_contact_sheet(folder: Path, frames, scheme, path: Path | None = None) -> Path:
    """Draw each chosen frame's face, enlarged, with its current points into ``folder/contact_sheet.png``."""
    import cv2  # noqa: PLC0415

    from keyshape.base.draw import contact_sheet, crop_around, draw_shape  # noqa: PLC0415
    from keyshape.base.formats.labels import pts_name, read_pts  # noqa: PLC0415

    tiles, caps = [], []
    for f in frames:
        im = cv2.imread(str(folder / "frames" / f"{f:06d}.png"), cv2.IMREAD_COLOR)
        if im is None:
            raise InputError(f"frame image {f:06d}.png missing or unreadable", folder / "frames")
        p = folder / pts_name(f)
        pts = read_pts(p) if p.is_file() else None
        collapsed = pts is not None and float(np.ptp(pts, axis=0).max()) < 1.0      # nothing to crop around
        if pts is not None and not collapsed:
            big = cv2.resize(im, None, fx=3, fy=3, interpolation=cv2.INTER_CUBIC)  # room for sub-pixel lines
            im, _ = crop_around(draw_shape(big, pts * 3 + 1, scheme), pts * 3 + 1, margin=0.3)
        tiles.append(im)
        caps.append(f"frame {f}" + (" (no points)" if pts is None else " (points collapsed)" if collapsed else ""))
    sheet = contact_sheet(tiles, caps, columns=4, tile_width=360)
    path = path or folder / "contact_sheet.png"
    _write_png(path, sheet)
    return path


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2  # noqa: PLC0415

    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise InputError("could not encode the image as PNG", path)
    with atomic_write(path, "wb") as fh:
        fh.write(buf.tobytes())


def prepare_label_folder(video: str | Path, out: str | Path, count: int = 12, scheme_name: str = "contours48",
                         use_prefill: bool = True, exclude=(), rng=0, quiet: bool = False,
                         frames=None) -> dict:
    """Choose ``count`` frames of ``video`` and make the label folder ``out`` (see module docstring).

    ``frames`` (zero-based indices) skips the choice and labels exactly those frames.

    Returns the session dict (``scheme``, ``video``, ``frames``, ``prefilled``).
    """
    import cv2  # noqa: PLC0415

    from keyshape.base.progress import Progress  # noqa: PLC0415
    from keyshape.base.formats.labels import pts_name, write_pts  # noqa: PLC0415
    from keyshape.tracker.labelling.frames import choose_frames, describe_video  # noqa: PLC0415
    from keyshape.base.schemes import load_scheme  # noqa: PLC0415
    from keyshape.base.formats.video import VideoReader  # noqa: PLC0415

    if int(count) < 1:
        raise InputError(f"--count must be at least 1, got {count}")
    scheme = load_scheme(scheme_name).full()            # with its auxiliary points (contours48: the nose)
    out = Path(out)
    reader = VideoReader(video)
    info = reader.info
    sess_path = out / SESSION_FILE
    landmarker = None
    if use_prefill:
        from keyshape.tracker.labelling.dlib_landmarker import DlibLandmarker  # noqa: PLC0415
        landmarker = DlibLandmarker()
    session = None
    pts68 = None                                        # dlib over the whole video, where the frames are chosen by it

    def checked(frames) -> list[int]:
        frames = sorted(set(int(f) for f in frames))
        if frames and (frames[0] < 0 or frames[-1] >= info.n_frames):
            raise InputError(f"--frames must be frame indices in 0..{info.n_frames - 1}", info.path)
        return frames

    def new_session(frames, **extra) -> dict:
        return {"scheme": scheme.name, "video": str(info.path.resolve()), "frames": [int(f) for f in frames],
                **extra, "note": "NNNNNN.pts holds the points of zero-based frame NNNNNN"}

    def min_gap(n: int) -> int:         # half a second, or less where the video is short
        return min(max(1, int(round(info.fps / 2))) if info.fps > 0 else 12, max(1, n // (2 * count)))

    if sess_path.is_file():
        from keyshape.base.formats.labels import read_session  # noqa: PLC0415
        old = read_session(out)
        if Path(old.get("video", "")).name == info.path.name and old["scheme"] in (scheme.name, scheme.base_name):
            session = old
            scheme = load_scheme(old["scheme"])     # a folder labelled before the nose points stays without them
            if frames is not None:      # --frames (or --more) on an existing folder: add those frames
                session["frames"] = sorted(set(session["frames"]) | set(checked(frames)))
        else:
            raise InputError(f"already holds labels of {old.get('video')} in scheme {old['scheme']}: "
                             f"choose another output folder", out)
    if session is None and frames is not None:
        frames = checked(frames)
        if not frames:
            raise InputError(f"--frames must be frame indices in 0..{info.n_frames - 1}", info.path)
        session = new_session(frames, prefilled=landmarker is not None)
    if session is None and landmarker is not None:
        # whole-video cues from dlib (eye closure, mouth, brows, head pose): cover what the face does
        from keyshape.tracker.labelling.dlib_landmarker import landmark_video_chained  # noqa: PLC0415
        from keyshape.tracker.labelling.frames import choose_frames_by_cues  # noqa: PLC0415
        from keyshape.tracker.labelling.frames import eye_profile  # noqa: PLC0415
        profiles: dict[int, np.ndarray] = {}

        def _eyes(i, gray, pts):
            profiles[i] = eye_profile(gray, pts)

        with Progress(info.n_frames, "dlib over the video", enabled=not quiet) as prog:
            pts68 = landmark_video_chained(video, landmarker, progress=lambda i, n: prog.update(), per_frame=_eyes)
        prof = np.full((len(pts68), 20), np.nan)
        for i, v in profiles.items():
            prof[i] = v
        if np.isfinite(pts68).all(axis=(1, 2)).sum() >= count:
            chosen = choose_frames_by_cues(pts68, count, min_gap=min_gap(len(pts68)), exclude=exclude,
                                           eye_profiles=prof)
            session = new_session(chosen, chosen_by="dlib cues", prefilled=True)
    if session is None:
        box = None
        if landmarker is not None:
            sample = reader.read_frames(np.linspace(0, max(info.n_frames - 1, 0), 9).astype(int))
            box = face_box([cv2.cvtColor(s, cv2.COLOR_BGR2GRAY) for s in sample], landmarker)
        with Progress(info.n_frames, "describing frames", enabled=not quiet) as prog:
            desc, sharp = describe_video(VideoReader(video, gray=True), box,
                                         progress=lambda i: prog.update())
        choice = choose_frames(desc, sharp, count, min_gap=min_gap(len(desc)), exclude=exclude, rng=rng)
        session = new_session(choice.frames, face_box=box, prefilled=landmarker is not None)
    frames = session["frames"]
    (out / "frames").mkdir(parents=True, exist_ok=True)
    images = reader.read_frames(frames)
    missing = [k for k, f in enumerate(frames) if not (out / pts_name(f)).is_file()]
    for f, im in zip(frames, images):
        png = out / "frames" / f"{f:06d}.png"
        if not png.is_file():
            _write_png(png, im)
    if missing:
        near = None if pts68 is None else pts68[[frames[k] for k in missing]]
        filled = (prefill(images[missing], scheme, landmarker, near) if landmarker is not None
                  else [None] * len(missing))
        h, w = images.shape[1:3]
        for k, pts in zip(missing, filled):
            write_pts(out / pts_name(frames[k]), pts if pts is not None else template_points(scheme, w, h))
        session["no_face"] = sorted(set(session.get("no_face", [])) |
                                    {frames[k] for k, p in zip(missing, filled) if p is None})
    with atomic_write(sess_path) as fh:
        json.dump(session, fh, indent=1)
    from keyshape.base.formats.labels import footage_record, write_footage  # noqa: PLC0415
    write_footage(out, footage_record(info.path))
    write_contact_sheet(out, frames, scheme)
    return session
