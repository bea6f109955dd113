"""Track one video on several cores: contiguous chunks in worker processes, stitched in frame order.

The frame range is split into ``jobs`` contiguous chunks; the worker of chunk ``k > 0`` seeks to ``warmup`` frames
before its own first frame and tracks those from a cold start; each worker streams its rows back to this process,
which emits them in frame order. At each seam chunk ``k + 1`` takes over when the overlap frames decoded alike
(checksums) and its warm-up agrees with the last ``SEAM_FRAMES`` frames emitted (success flags, every point within
``seam_tol`` px); else this process tracks on from chunk ``k``'s final tracker state until they agree. Smoothing
runs here, on the stitched stream. Workers are spawned processes on one thread each. docs/tracker.md, ``--jobs``.
"""
from __future__ import annotations

import os
import pickle
import queue as queue_mod
import signal
import threading
import zlib
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from keyshape.base.errors import InputError, KeyshapeError
from keyshape.base.formats.video import VideoReader
from keyshape.tracker.defaults import TrackOptions

#: frames before a seam on which the chunk after it must agree with the frames emitted
SEAM_FRAMES = 5
#: rows a worker sends at a time
BATCH = 16


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system says, else ``os.cpu_count``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def plan_chunks(start: int, stop: int, jobs: int, warmup: int, min_frames: int = 1) -> list[tuple[int, int, int]]:
    """Split frames ``start``..``stop`` (exclusive) into at most ``jobs`` contiguous chunks.

    Returns ``(first decoded, first own, end)`` per chunk: the warm-up of chunk ``k > 0`` starts
    ``warmup`` frames before its own frames (not before ``start``). Chunks have at least
    ``min_frames`` own frames (fewer chunks otherwise, one at least).
    """
    n = max(0, stop - start)
    jobs = max(1, min(int(jobs), n // max(1, int(min_frames)) if n else 1))
    bounds = [start + (n * k) // jobs for k in range(jobs + 1)]
    return [(max(start, bounds[k] - (warmup if k else 0)), bounds[k], bounds[k + 1]) for k in range(jobs)]


@dataclass
class Seam:
    """How one seam was crossed: at ``frame``, the points of the chunk after it against the frames
    emitted before it (``max_px`` over the last ``SEAM_FRAMES`` frames, NaN where they could not be
    compared; ``checks``: each try's), whether the overlap frames decoded the same (``frames_equal``), and
    how many frames this process tracked sequentially before handing over (``repaired``; 0: none)."""

    frame: int
    max_px: float = float("nan")
    frames_equal: bool = True
    repaired: int = 0
    checks: list = field(default_factory=list)


def _crc(frame: np.ndarray) -> int:
    return zlib.crc32(np.ascontiguousarray(frame))


def _worker(k: int, video: str, inbox, lo: int, own: int, end: int | None, warmup: int,
            tracker_options: dict, out) -> None:
    """Track frames ``lo``..``end`` of ``video`` with the pickled model taken from ``inbox``; send rows (and the
    overlap frames' checksums) to ``out``."""
    os.environ["OPENCV_FFMPEG_THREADS"] = "1"          # the decoder of the video opened below: one thread
    try:
        from keyshape.tracker.eigenpoints import to_gray
        from keyshape.tracker.fitting import Tracker, single_threaded

        model = pickle.loads(inbox.get())
        reader = VideoReader(video, gray=True, luma=True)     # as iter_track_chunked's own reader (the seams' checksums)
        rows: list = []
        hashes: dict = {}
        hash_from = None if end is None else end - warmup

        def send():
            if rows:
                out.put(("rows", k, rows[:], hashes.copy()))
                rows.clear()
                hashes.clear()

        with single_threaded():
            tracker = Tracker(model, **tracker_options)       # its QR factorisations on one thread too
            # the first chunk decodes from the video's start, as a sequential run does (nothing checks it);
            # the others seek, checked at their seams
            for i, frame in reader.frames(lo, end, seek=k > 0):
                if i < own or (hash_from is not None and i >= hash_from):
                    hashes[i] = _crc(frame)
                r = tracker.step(to_gray(frame), i)
                rows.append((i, r.points, r.pose, r.residual, r.confidence, r.success, r.iterations))
                if len(rows) >= BATCH:
                    send()
        send()
        out.put(("done", k, tracker.state(), (reader.n_read, reader.truncated)))
    except BaseException as exc:  # noqa: BLE001 - handed to the parent, which raises it
        out.put(("error", k, isinstance(exc, KeyshapeError), f"{exc}" if isinstance(exc, KeyshapeError)
                 else f"{type(exc).__name__}: {exc}"))


def _agree(emitted: deque, rows: dict, seam_tol: float) -> tuple[bool, float]:
    """Whether ``rows`` (index -> row) agree with the last ``SEAM_FRAMES`` ``emitted`` rows
    ``(index, points, success)``; also the largest point difference (px) of those frames."""
    if len(emitted) < SEAM_FRAMES:
        return False, float("nan")
    diffs = []
    ok = True
    for i, pts, success in emitted:
        r = rows.get(i)
        if r is None:
            return False, float("nan")
        if bool(r[5]) != bool(success):
            ok = False
        elif success:
            diffs.append(np.abs(r[1] - pts).max(axis=-1))
    if not emitted[-1][2]:
        ok = False              # a lost last frame: the trackers' search states may differ
    mx = float(np.nanmax(np.concatenate(diffs))) if diffs else float("nan")
    return ok and bool(diffs) and mx <= seam_tol, mx


def _resume(reader: VideoReader, i: int, stop: int | None, known: dict):
    """Frames ``i`` to ``stop`` of ``reader`` for a seam's repair: from a seek to ``SEAM_FRAMES`` frames
    before ``i`` when those decode to the checksums ``known`` (index -> :func:`_crc`) of the frames
    emitted there (the seek was frame-exact), else decoded from the video's start (``seek=False``)."""
    back = range(i - SEAM_FRAMES, i)
    if i >= SEAM_FRAMES and all(f in known for f in back):
        frames = reader.frames(back[0], stop, seek=True)
        for f in back:
            got = next(frames, None)
            if got is None or got[0] != f or _crc(got[1]) != known[f]:
                frames.close()
                break
        else:
            return frames
    return reader.frames(i, stop, seek=False)


def iter_track_chunked(video, model, options: TrackOptions | None = None, *, warmup: int = 30, seam_tol: float = 0.05,
                       reader: VideoReader | None = None, progress=None, seams: list | None = None):
    """:func:`~keyshape.tracker.commands.iter_track` on ``jobs`` worker processes (frames not kept).

    Yields ``(points, FrameResult, None)`` in frame order, smoothed by ``smooth`` here; see the
    module's description for the seams. ``progress`` (a :class:`~keyshape.base.progress.Progress`)
    counts the frames the workers tracked as they arrive; ``seams`` (a list) receives one
    :class:`Seam` per seam. Afterwards ``reader.n_read`` and ``reader.truncated`` describe the decode
    as a sequential run's would. On Ctrl-C the workers are stopped, the frames the smoother holds
    are yielded, and ``KeyboardInterrupt`` is raised again.

    Parameters
    ----------
    options : :class:`~keyshape.tracker.defaults.TrackOptions` (the range, the smoothing, ``jobs``: worker
        processes (chunks); default: its defaults with 2 jobs)
    warmup : frames each chunk after the first tracks before its own first frame (>= ``SEAM_FRAMES``)
    seam_tol : largest point difference (px) at which a chunk's warm-up counts as converged onto
        the frames emitted before it
    """
    import multiprocessing as mp

    from keyshape.tracker.eigenpoints import to_gray
    from keyshape.tracker.fitting import FrameResult, Tracker, single_threaded
    from keyshape.tracker.smoothing import StreamSmoother

    o = options if options is not None else TrackOptions(jobs=2)
    smooth, start, stop, jobs, tracker_options = o.smooth, o.start, o.stop, o.jobs, o.tracker
    if warmup < SEAM_FRAMES:
        raise InputError(f"warmup {warmup}: need at least {SEAM_FRAMES} frames to check the seams")
    reader = reader or VideoReader(video, gray=True, luma=True)
    options = dict(tracker_options or {})
    n_total = reader.info.n_frames
    last = stop if stop is not None else n_total
    chunks = plan_chunks(start, last, jobs, warmup, min_frames=max(SEAM_FRAMES, 1))
    n_chunks = len(chunks)
    ends = [c[2] for c in chunks]
    if stop is None:
        ends[-1] = None                               # the last chunk reads to the video's real end
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    # the model goes to the workers through a queue, not as a process argument: start() would wait for each child
    # to import keyshape before starting the next
    inbox = ctx.Queue()
    for q in (out, inbox):
        q.cancel_join_thread()      # never wait at exit for a queue's feeder thread, even after an interrupt
    model_bytes = pickle.dumps(model, protocol=pickle.HIGHEST_PROTOCOL)
    procs = []
    main = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None   # children ignore Ctrl-C from birth
    try:
        for k, (lo, own, _) in enumerate(chunks):
            inbox.put(model_bytes)
            p = ctx.Process(target=_worker, args=(k, str(reader.path), inbox, lo, own, ends[k], warmup,
                                                  options, out), daemon=True, name=f"keyshape-track-{k}")
            p.start()
            procs.append(p)
    finally:
        if main:
            signal.signal(signal.SIGINT, old)

    rows: list[dict] = [{} for _ in chunks]
    hashes: list[dict] = [{} for _ in chunks]
    done: list = [None] * n_chunks                     # (final tracker state, (n_read, truncated))

    def pump() -> None:
        try:
            msg = out.get(timeout=0.2)
        except queue_mod.Empty:
            for k, p in enumerate(procs):
                if done[k] is None and not p.is_alive() and p.exitcode not in (0, None):
                    raise RuntimeError(f"tracking worker {k} died (exit code {p.exitcode}; out of memory?)")
            return
        kind, k = msg[0], msg[1]
        if kind == "rows":
            for r in msg[2]:
                rows[k][r[0]] = r
            hashes[k].update(msg[3])
            if progress is not None:
                progress.update(sum(1 for r in msg[2] if r[0] >= chunks[k][1]))
        elif kind == "done":
            done[k] = (msg[2], msg[3])
        else:
            raise (InputError(msg[3], reader.path) if msg[2] else RuntimeError(f"tracking worker {k}: {msg[3]}"))

    def has(k: int, i: int) -> bool:
        """Wait until chunk ``k`` has sent frame ``i`` or finished; whether it has frame ``i``."""
        while i not in rows[k] and done[k] is None:
            pump()
        return i in rows[k]

    def owner(i: int) -> int:
        k = 0
        while k + 1 < n_chunks and chunks[k + 1][1] <= i:
            k += 1
        return k

    def result(r) -> FrameResult:
        return FrameResult(int(r[0]), r[1], r[2], float(r[3]), float(r[4]), bool(r[5]), int(r[6]))

    smoother = StreamSmoother(smooth, reader.info.fps)
    emitted: deque = deque(maxlen=SEAM_FRAMES)          # (index, points, success) of the last frames emitted
    emitted_hash: dict = {}                             # checksums of the last ``warmup`` frames emitted
    seam_of: dict[int, Seam] = {}
    interrupted: KeyboardInterrupt | None = None
    src: int | None = 0                                 # the chunk whose rows are emitted; None: tracking here
    seq = seq_frames = None
    i = chunks[0][1]
    try:
        with single_threaded():
            while stop is None or i < stop:
                o = owner(i)
                if src != o:
                    # hand over to chunk o where the overlap frames decoded alike and the last frames agree
                    seam = seam_of.get(o)
                    if seam is None:
                        seam = seam_of[o] = Seam(i)
                        if seams is not None:
                            seams.append(seam)
                    ok = False
                    if seam.frames_equal and has(o, i):
                        seam.frames_equal = all(hashes[o].get(f, h) == h for f, h in emitted_hash.items())
                        ok, mx = _agree(emitted, rows[o], seam_tol)
                        seam.checks.append(mx)
                        seam.max_px = seam.checks[0]
                        ok = ok and seam.frames_equal
                    if ok:
                        src, seq, seq_frames = o, None, None
                    elif src is not None:
                        # not converged: carry on sequentially from the chunk before's final state
                        while done[src] is None:
                            pump()
                        seq = Tracker(model, **options)
                        seq.restore(done[src][0])
                        seq_frames = _resume(reader, i, stop, emitted_hash)
                        src = None
                if src is None:
                    nxt = next(seq_frames, None)
                    if nxt is None:
                        break
                    res = seq.step(to_gray(nxt[1]), i)
                    seam_of[o].repaired += 1
                    h = _crc(nxt[1])
                else:
                    if not has(src, i):
                        break
                    res = result(rows[src].pop(i))
                    h = hashes[src].pop(i, None)
                emitted.append((i, res.points, res.success))
                emitted_hash.pop(i - warmup, None)
                if h is not None:
                    emitted_hash[i] = h
                yield from ((pts, rr, None) for pts, rr in smoother.push(res.points, res))
                i += 1
    except KeyboardInterrupt as exc:
        interrupted = exc
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(5.0)
        for q in (out, inbox):
            q.close()
    yield from ((pts, rr, None) for pts, rr in smoother.flush())
    if interrupted is not None:
        raise interrupted
    reader.n_read = i
    reader.truncated = stop is None and n_total > 0 and i < n_total
