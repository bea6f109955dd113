"""File-level drivers of ``keyshape train`` and ``keyshape track`` (video and label files in, files out).

The algorithms (:mod:`keyshape.tracker.eigenpoints`, :mod:`keyshape.tracker.fitting`) never open
files; this module does, streaming the video so that memory does not grow
with its length, writing every output atomically, and keeping what was
tracked when the video is truncated or the run is interrupted (Ctrl-C).
"""
from __future__ import annotations

import contextlib
import os
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.files import _tmp_sibling, atomic_write, check_outputs, commit, partial_name, sha256_file
from keyshape.base.progress import Progress
from keyshape.tracker.defaults import TrackOptions
from keyshape.tracker.eigenpoints import AppearanceModel, to_gray
from keyshape.base.formats.tracks import PARTIAL_MARK, Tracks, TracksWriter, meta_line, meta_path, write_meta
from keyshape.base.formats.labels import labels_scheme, read_labels
from keyshape.base.schemes import load_scheme
from keyshape.base.formats.video import VideoReader, video_info, video_writer


def fit_model(video, labels, scheme: str | None = None, n_components: int | None = None, n_morphs: int = 120,
              rng=0) -> AppearanceModel:
    """Fit an :class:`AppearanceModel` to labelled frames of ``video``.

    Parameters
    ----------
    video : path of the video the labels belong to
    labels : a folder of ``NNNNNN.pts`` files, or ``(frames (n,), shapes (n, n_points, 2))`` arrays
    scheme : as :class:`AppearanceModel`; None: the scheme the labels folder was made in by
        ``keyshape label`` (its ``session.json``), else ``contours48``; labels that carry the scheme's
        auxiliary points too (``Scheme.auxiliary``: the nose, 48 + 5 points) train its
        :meth:`~keyshape.base.schemes.Scheme.full` form, whose tracks carry them in their own columns
    n_components, n_morphs, rng : as :class:`AppearanceModel`

    Raises
    ------
    InputError
        Labels of the wrong point count, for frames past the video's end or far outside the picture
        (naming the labels folder or file).
    """
    if scheme is None:
        scheme = (labels_scheme(labels) if isinstance(labels, (str, Path)) else None) or "contours48"
    sch = load_scheme(scheme)
    if isinstance(labels, (str, Path)):
        source = Path(labels)
        frames, shapes = read_labels(labels)
        sch = _labelled_scheme(sch, shapes)
        if shapes.shape[1] != sch.n_points:
            raise InputError(f"labels of {shapes.shape[1]} points, expected {sch.n_points} for scheme {sch.name!r}"
                             + (f" ({sch.full().n_points} with its {'+'.join(sch.auxiliary)} points)"
                                if sch.auxiliary and not sch.n_core else ""), source)
    else:
        source = None
        frames, shapes = (np.asarray(a) for a in labels)
        frames = frames.astype(np.int64)
        shapes = shapes.astype(np.float64)
        sch = _labelled_scheme(sch, shapes)
        if shapes.ndim != 3 or shapes.shape[1:] != (sch.n_points, 2) or len(frames) != len(shapes):
            raise InputError(f"labels: expected frames (n,) and shapes (n, {sch.n_points}, 2) for scheme "
                             f"{sch.name!r}, got {frames.shape} and {shapes.shape}")
    info = video_info(video)
    if source is not None:
        frames, shapes = _without_generic_shapes(source, frames, shapes, sch, info)
    if info.n_frames > 0 and frames.max() >= info.n_frames:
        bad = [int(f) for f in frames if f >= info.n_frames]
        raise InputError(f"labels for frames {bad[:5]} but the video has {info.n_frames} frames "
                         f"(frames are numbered from 0)", source)
    check_label_geometry(frames, shapes, source)
    images = VideoReader(video, gray=True, luma=True).read_frames(frames)     # as iter_track decodes them
    h, w = images.shape[1:3]
    outside = (shapes[..., 0] < -0.5 * w) | (shapes[..., 0] > 1.5 * w) | (shapes[..., 1] < -0.5 * h) | \
              (shapes[..., 1] > 1.5 * h)
    if outside.any():
        f = int(frames[np.flatnonzero(outside.any(1))[0]])
        raise InputError(f"points far outside the {w}x{h} frame: are these labels for this video?",
                         None if source is None else source / f"{f:06d}.pts")
    return AppearanceModel(sch, n_components=n_components, n_morphs=n_morphs, rng=rng).fit(list(images), shapes)


def _without_generic_shapes(source: Path, frames: np.ndarray, shapes: np.ndarray, scheme, info):
    """The labels but those still at the generic shape where dlib found no face (``session.json``'s ``no_face``),
    saying which; raises where none is left."""
    from keyshape.base.formats.labels import read_session
    from keyshape.tracker.labelling.prepare import template_points

    if not (source / "session.json").is_file():
        return frames, shapes
    no_face = set(read_session(source).get("no_face", []))
    if not no_face:
        return frames, shapes
    generic = template_points(scheme, info.width, info.height)
    left = np.array([not (int(f) in no_face and np.allclose(s, generic, atol=1e-3)) for f, s in zip(frames, shapes)])
    if not left.all():
        skipped = [int(f) for f in frames[~left]]
        if not left.any():
            raise InputError(f"every label is still the generic shape dlib's pre-fill left where it found no face "
                             f"(frames {skipped}): place their points (keyshape label VIDEO -o {source} --serve)",
                             source)
        print(f"keyshape train: frames {skipped} still hold the generic shape (dlib found no face there): not "
              f"trained on; place their points with keyshape label --serve")
    return frames[left], shapes[left]


def model_fingerprint(model: AppearanceModel) -> str:
    """A short, stable identity of a trained model: ``sha256:`` of its learnt arrays (16 hex digits).

    Written into the tracks it makes (``# keyshape-tracks`` line) and from there into
    KEYS.json, so ``keyshape decompose`` can refuse keys chosen with another model.
    """
    import hashlib

    h = hashlib.sha256()
    for k in AppearanceModel._ARRAYS:
        a = np.ascontiguousarray(getattr(model, k))
        h.update(k.encode() + str(a.shape).encode() + a.astype(np.float64).tobytes())
    return "sha256:" + h.hexdigest()[:16]


class _Raised:
    """An exception raised by :func:`_prefetched`'s producer, handed to the consumer."""

    def __init__(self, exc: BaseException):
        self.exc = exc


def _prefetched(items, depth: int = 8, batch: int = 4):
    """Iterate over ``items`` while a background thread produces up to ``depth`` of them ahead.

    The producer hands them over in lists of ``batch`` (each hand-over passes the GIL back and forth: lists cost
    the tracker less CPU a frame than single items). Its exceptions are re-raised in the consumer after the items
    produced before them; leaving the loop early stops the producer and closes ``items`` in its thread.
    """
    import threading

    from keyshape.base.interrupts import Handoff, start_thread

    q = Handoff(max(1, depth // max(1, batch)))
    end = object()

    def produce():
        it = iter(items)
        buf: list = []
        try:
            for x in it:
                buf.append(x)
                if len(buf) >= batch:
                    if not q.put(buf):
                        break
                    buf = []
            else:
                if not buf or q.put(buf):
                    q.put(end)
        except BaseException as exc:  # noqa: BLE001 - handed over to the consumer
            if not buf or q.put(buf):
                q.put(_Raised(exc))
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()

    thread = threading.Thread(target=produce, name="keyshape-decode", daemon=True)
    try:
        start_thread(thread)
        while True:
            x = q.get()             # Ctrl-C / SIGTERM here cannot wedge the hand-over (interrupts)
            if x is end:
                break
            if isinstance(x, _Raised):
                raise x.exc
            yield from x
    finally:
        q.close()
        if thread.ident is not None:      # started (an interrupt may land inside start())
            thread.join()


def _labelled_scheme(scheme, shapes: np.ndarray):
    """``scheme``'s :meth:`~keyshape.base.schemes.Scheme.full` form where the labels ``shapes`` (n, n_points, 2)
    carry its auxiliary points too (the nose), else ``scheme``."""
    full = scheme.full()
    return full if shapes.ndim == 3 and shapes.shape[1] == full.n_points else scheme


def _with_gray(frames, start: int = 0):
    """``(index, frame, gray)`` for each ``(index, frame)`` of ``frames`` from ``start`` on (before it the
    frame twice, unconverted): the gray conversion :class:`~keyshape.tracker.eigenpoints.Pyramid` would do,
    done where the frames are produced (the decode thread of :func:`iter_track`)."""
    for i, frame in frames:
        yield i, frame, (to_gray(frame) if i >= start else frame)


def check_frame_size(model: AppearanceModel, width: int, height: int, video=None) -> None:
    """Refuse frames of another size than the model's labelled frames (a model trained on 640x480
    tracks a 320x240 video wrongly without losing a frame); models without a recorded size pass."""
    want = getattr(model, "image_size_", None)
    if want is not None and width and height and (int(width), int(height)) != tuple(want):
        raise InputError(f"the video's frames are {width}x{height} but the model was trained on "
                         f"{want[0]}x{want[1]} frames: track video of the labelled footage's size "
                         "(or label and train on this size)", video)


def iter_track(video, model: AppearanceModel, options: TrackOptions | None = None, *, keep_frames: bool = False,
               reader: VideoReader | None = None, progress: Progress | None = None, seams: list | None = None):
    """Track frames ``start`` to ``stop`` (exclusive; None: the end) of ``video``, one at a time
    (``options``: a :class:`~keyshape.tracker.defaults.TrackOptions`, default its defaults).

    Yields ``(points (n_points, 2), FrameResult, frame or None)`` in frame order, after the temporal
    smoothing. On Ctrl-C the frames the smoother still holds are yielded, then ``KeyboardInterrupt`` is raised again.
    With ``decode_thread`` (default) a background thread decodes and converts to gray up to 8 frames ahead
    (:func:`_prefetched`; the same gray levels as the tracker's own conversion).

    ``jobs`` above 1 tracks contiguous chunks in that many worker processes, stitched in frame order
    (:func:`keyshape.tracker.chunked.iter_track_chunked`; frames not kept); ``progress`` then counts the frames as
    the workers track them (with one job the caller counts those yielded) and ``seams`` (a list) receives a
    :class:`keyshape.tracker.chunked.Seam` per seam.
    """
    from keyshape.tracker.fitting import Tracker, single_threaded
    from keyshape.tracker.smoothing import StreamSmoother

    o = options if options is not None else TrackOptions()
    smooth, start, stop, jobs, decode_thread = o.smooth, o.start, o.stop, o.jobs, o.decode_thread
    reader = reader or VideoReader(video, gray=not keep_frames, luma=True)
    check_frame_size(model, reader.info.width, reader.info.height, video)
    if jobs > 1:
        if keep_frames:
            raise InputError(f"jobs={jobs}: the frames are decoded in worker processes and not kept (an overlay "
                             "needs one job)")
        from keyshape.tracker.chunked import iter_track_chunked

        yield from iter_track_chunked(video, model, o, reader=reader, progress=progress, seams=seams)
        return
    smoother = StreamSmoother(smooth, reader.info.fps)
    interrupted: KeyboardInterrupt | None = None
    try:
        # OpenCV and BLAS single-threaded while tracking and building the tracker (its QR factorisations):
        # less CPU per frame, the same points; restored when the loop ends or the generator is closed
        with single_threaded():
            tracker = Tracker(model, **(o.tracker or {}))
            frames = _prefetched(_with_gray(reader, start)) if decode_thread else ((i, f, f) for i, f in reader)
            try:
                for i, frame, gray in frames:
                    if i < start:
                        continue
                    if stop is not None and i >= stop:
                        break
                    res = tracker.step(gray, i)
                    yield from ((pts, r, fr) for pts, (r, fr) in
                                smoother.push(res.points, (res, frame if keep_frames else None)))
            finally:
                # stop and join the decode thread now: a daemon thread still decoding in OpenCV at exit is
                # ended inside C++ (SIGABRT instead of exit status 143)
                frames.close()
    except KeyboardInterrupt as exc:
        interrupted = exc
    yield from ((pts, r, fr) for pts, (r, fr) in smoother.flush())
    if interrupted is not None:     # the frames the smoother held are out; now stop the caller too
        raise interrupted


def track_frames(video, model, options: TrackOptions | None = None, scheme=None, show_progress: bool = False) -> Tracks:
    """Track ``video`` with ``model`` (an AppearanceModel or a model file) into :class:`Tracks` in memory.

    The same per-frame results as :func:`track_video` (which streams them to a file instead), with or
    without the decode-ahead thread (``options.decode_thread``, :func:`iter_track`). ``options.jobs``: worker
    processes tracking contiguous chunks of the range (:func:`iter_track`; None: :func:`auto_jobs`); 1 (default)
    tracks in this process, as a batch worker must (it is one core already).
    """
    o = options if options is not None else TrackOptions()
    start, stop = o.start, o.stop
    if not isinstance(model, AppearanceModel):
        model = AppearanceModel.load(model, scheme)
    reader = VideoReader(video, gray=True, luma=True)
    fps = reader.info.fps
    rows = []
    n_total = (stop if stop is not None else reader.info.n_frames) - start
    jobs = auto_jobs(n_total) if o.jobs is None else int(o.jobs)
    with Progress(n_total if n_total > 0 else None, desc="keyshape track", enabled=show_progress) as prog:
        for pts, res, _ in iter_track(video, model, replace(o, jobs=jobs), reader=reader, progress=prog):
            rows.append((res.index, res.confidence, res.success, pts, res.pose))
            if jobs <= 1:
                prog.update()
    if stop is not None and reader.n_read < stop and not rows:
        raise InputError(f"frame range {start}-{stop} is past the video's end ({reader.n_read} frames)", video)
    if not rows:
        raise InputError(f"no frames from {start} on (the video has {reader.n_read} frames)", video)
    frame = np.array([r[0] for r in rows], dtype=np.int64)
    points, aux = model.scheme_.split(np.stack([r[3] for r in rows]))
    return Tracks(frame, frame / fps, np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                  points, np.stack([r[4] for r in rows]), _tracks_meta(model, reader.info), aux)


def _tracks_meta(model: AppearanceModel, info) -> dict:
    """The tracks' ``# keyshape-tracks`` metadata of ``model`` on a video of ``info``."""
    return {"model": model_fingerprint(model), "scheme": model.scheme_.base_name,
            "image_size": [int(info.width), int(info.height)], "fps": float(info.fps)}


#: the fewest frames a chunk gets from :func:`auto_jobs` (a worker's start, about a second, and its
#: warm-up cost what tracking a few hundred frames does)
AUTO_MIN_FRAMES = 500


def auto_jobs(n_frames: int) -> int:
    """Worker processes for ``n_frames`` frames when none are asked for: one per core this process may
    use, with at least :data:`AUTO_MIN_FRAMES` frames each (1 for an unknown length)."""
    from keyshape.tracker.chunked import available_cores

    return max(1, min(available_cores(), int(n_frames) // AUTO_MIN_FRAMES)) if n_frames and n_frames > 0 else 1


def check_label_geometry(frames: np.ndarray, shapes: np.ndarray, labels_dir) -> None:
    """Refuse degenerate labels: points collapsed onto one spot or one line, or mostly coincident
    (a half-finished label file), naming the file."""
    for f, pts in zip(frames, shapes):
        name = Path(labels_dir) / f"{int(f):06d}.pts" if labels_dir is not None else None
        c = pts - pts.mean(0)
        ev = np.linalg.eigvalsh(c.T @ c / len(pts))
        if ev[-1] < 1.0:
            raise InputError(f"the {len(pts)} points are collapsed onto one spot (spread "
                             f"{np.sqrt(max(ev[-1], 0)):.2g} px): not a labelled face", name)
        if ev[0] < 1e-6 * ev[-1]:
            raise InputError(f"the {len(pts)} points lie on one line: not a labelled face", name)
        distinct = len(np.unique(np.round(pts, 1), axis=0))
        if distinct < 0.75 * len(pts):
            raise InputError(f"only {distinct} of {len(pts)} points are distinct (coincident points): "
                             "unfinished or corrupt label file", name)


@dataclass
class TrackSummary:
    n_frames: int
    expected: int
    n_lost: int
    fps: float
    truncated: bool
    interrupted: bool
    message: str
    terminated: bool = False
    seams: list = field(default_factory=list)   # jobs > 1: how each seam was crossed (chunked.Seam)


def track_video(video, model, output, overlay=None, options: TrackOptions | None = None, show_progress: bool = True,
                scheme=None) -> TrackSummary:
    """Track ``video`` with ``model`` (an AppearanceModel or a model file) into a tracks CSV at ``output``.

    Frames are decoded, tracked, written and (with ``overlay``) drawn one at a
    time. A truncated video yields the frames that decoded; Ctrl-C stops the
    loop and keeps the rows written so far (the summary says which). ``options``: a
    :class:`~keyshape.tracker.defaults.TrackOptions` (its range is not used: the whole video is tracked);
    ``options.jobs``: worker processes tracking contiguous chunks of the video (:func:`iter_track`; None:
    :func:`auto_jobs`, one with ``overlay``); rows are written in frame order as the chunks are stitched, so an
    interrupted run keeps the frames stitched so far (the first chunk's tracked frames at least).
    """
    import cv2

    from keyshape.base.draw import draw_shape

    check_outputs([output, meta_path(output), overlay],
                  inputs=[video, model if not isinstance(model, AppearanceModel) else None])
    if not isinstance(model, AppearanceModel):
        model = AppearanceModel.load(model, scheme)
    reader = VideoReader(video, gray=not overlay, luma=True)      # the overlay draws on the colour frames
    info = reader.info
    o = options if options is not None else TrackOptions()
    jobs = (1 if overlay else auto_jobs(info.n_frames)) if o.jobs is None else int(o.jobs)
    if overlay and jobs > 1:
        raise InputError(f"--overlay draws on the frames as they are tracked: it needs --jobs 1, not {jobs}")
    n_lost = 0
    seams: list = []
    interrupted: KeyboardInterrupt | None = None
    prog = Progress(info.n_frames or None, desc="keyshape track", enabled=show_progress)
    t0 = time.perf_counter()
    output = Path(output)
    tmp_csv = _tmp_sibling(output)
    tmp_vid = _tmp_sibling(Path(overlay), suffix=Path(overlay).suffix) if overlay else None
    try:
        with contextlib.ExitStack() as stack:
            f = stack.enter_context(open(tmp_csv, "w", newline="\n"))
            sch = model.scheme_
            meta = _tracks_meta(model, info)
            writer = TracksWriter(f, sch.core, {g: len(src) for g, src in sch.auxiliary.items()} if sch.n_core else None)
            vw = stack.enter_context(video_writer(tmp_vid, info.fps, (info.width, info.height))) if overlay else None
            try:
                for pts, res, frame in iter_track(video, model, replace(o, start=0, stop=None, jobs=jobs),
                                                  keep_frames=vw is not None, reader=reader, progress=prog,
                                                  seams=seams):
                    n_lost += not res.success
                    writer.write(res.index, res.index / info.fps, res.confidence, res.success, pts, res.pose)
                    if vw is not None:
                        img = draw_shape(frame, pts, model.scheme_) if res.success else frame.copy()
                        if not res.success:
                            cv2.putText(img, "lost", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 255), 2)
                        vw.write(img)
                    if jobs <= 1:
                        prog.update()
            except KeyboardInterrupt as exc:
                interrupted = exc
            prog.close()
            f.flush()
            os.fsync(f.fileno())
        n = writer.n_rows
        if interrupted is None:
            write_meta(output, meta, sha256_file(tmp_csv))
            commit(tmp_csv, output)
            if overlay:
                commit(tmp_vid, overlay)
        elif n:
            # the earlier complete outputs stay; what was tracked goes to NAME.partial.csv, marked partial
            part = partial_name(output)
            with atomic_write(part) as pf, open(tmp_csv) as src:
                pf.write(f"{PARTIAL_MARK} interrupted after {n} of {info.n_frames or '?'} frames; "
                         "read it with --accept-partial\n" + meta_line(meta))
                shutil.copyfileobj(src, pf)
            if overlay:
                commit(tmp_vid, partial_name(overlay))
    finally:
        tmp_csv.unlink(missing_ok=True)
        if tmp_vid is not None:
            tmp_vid.unlink(missing_ok=True)
    dt = time.perf_counter() - t0
    truncated = (interrupted is None) and reader.truncated
    if interrupted is None:
        msg = (f"keyshape track: {n} frames, {n_lost} lost, {n / max(dt, 1e-9):.0f} frames/s"
               + (f" ({jobs} jobs{_seams_text(seams)})" if jobs > 1 else "") + f" -> {output}"
               + (f" and {overlay}" if overlay else ""))
    elif not n:                         # stopped before a frame was ready: no partial file without rows
        msg = (f"keyshape track: interrupted before any frame was tracked: nothing written; {output} "
               f"{'is untouched' if output.exists() else 'was not written'}")
    else:
        msg = (f"keyshape track: interrupted: tracks written for frames 0-{n - 1} only, to "
               f"{partial_name(output)} (marked partial); {output} "
               f"{'is untouched' if output.exists() else 'was not written'}")
    return TrackSummary(n, info.n_frames, n_lost, n / max(dt, 1e-9), truncated, interrupted is not None, msg,
                        terminated=type(interrupted).__name__ == "Terminated", seams=seams)


def _seams_text(seams: list) -> str:
    """``; seams: max 0.02 px, 0 frames re-tracked`` for the summary line (empty without seams)."""
    if not seams:
        return ""
    mx = max((s.max_px for s in seams if s.max_px == s.max_px), default=float("nan"))
    return f"; seams: points within {mx:.3f} px, {sum(s.repaired for s in seams)} frames re-tracked here"
