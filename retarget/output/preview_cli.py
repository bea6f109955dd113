"""``keyshape preview``: a take's footage with its contours beside the shaded rig driven by its curves."""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    """Add ``preview`` to ``subparsers``."""
    p = subparsers.add_parser(
        "preview", help="side-by-side video of a take: footage with contours | the shaded rig (and a contact sheet)",
        description="Render the footage with its tracked contours beside the rig driven by the take's curves "
                    "(a curves CSV of 'keyshape solve' or 'keyshape retarget ... --poses'), with a progress bar.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("video", help="the take's video")
    p.add_argument("--tracks", required=True, help="the take's tracks CSV (contours drawn on the footage)")
    p.add_argument("--curves", required=True, help="rig curves CSV (frame,time,<rig shape>,...; the head's columns turn it)")
    p.add_argument("--rig", nargs="+", required=True, metavar="DIR|FILE", help="the rig (folder of shape OBJs)")
    p.add_argument("--neutral", default=None, help="the rig's neutral OBJ (default: found in the folder)")
    p.add_argument("--frames", default=None, metavar="A:B", help="frame range, B exclusive (default: all)")
    p.add_argument("--size", type=int, default=None,
                   help="height of the output in pixels (default: the video's height)")
    p.add_argument("--sheet", default=None, help="also write a contact sheet (actor | character), .jpg or .png")
    p.add_argument("--contours", action=argparse.BooleanOptionalAction, default=None,
                   help="draw the rig's own lid, brow and lip contours over it (default: when the rig's "
                        "landmarks are known: shipped for ICT-FaceKit, or --landmarks)")
    p.add_argument("--landmarks", default=None,
                   help="rig landmark JSON for --contours (default: the shipped one for ICT-FaceKit rigs)")
    p.add_argument("--compare", default=None, metavar="CURVES.csv",
                   help="a second set of rig curves (another solver, another tool's) rendered in a third panel")
    p.add_argument("-o", "--output", default=None, help="OUT.mp4 / .avi (optional with --sheet)")
    p.set_defaults(func=run)


def _curves_on_rig(path, rig):
    """(frames, (n_frames, n_shapes) curves in the rig's shape order, head rotations or None) of a curves CSV."""
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.weights import read_weights
    from keyshape.retarget.output.preview import head_rotations

    frames, names, c, _ = read_weights(path)
    found = [(j, names.index(n)) for j, n in enumerate(rig.names) if n in names]
    if not found:
        raise InputError("no column names a rig shape", path)
    curves = np.zeros((len(frames), rig.n_shapes))
    curves[:, [j for j, _ in found]] = c[:, [k for _, k in found]]
    return frames, curves, head_rotations(names, c)


def run(args) -> int:
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.tracks import check_frame_size, read_tracks
    from keyshape.base.formats.video import video_info
    from keyshape.retarget.defaults import PreviewOptions
    from keyshape.retarget.rig.model import load_rig

    _check_outputs(args.output, args.sheet, size=args.size)
    rig = load_rig(args.rig, args.neutral)
    frames, curves, head = _curves_on_rig(args.curves, rig)
    compare = None
    if args.compare:
        f2, c2, h2 = _curves_on_rig(args.compare, rig)
        row2 = {int(f): i for i, f in enumerate(f2)}
        gone = [int(f) for f in frames if int(f) not in row2]
        if gone:
            raise InputError(f"has no row for frame {gone[0]} (of {len(gone)} frames of the take)", args.compare)
        idx = np.array([row2[int(f)] for f in frames])
        compare = (c2[idx], h2[idx] if h2 is not None else head)
    tracks = read_tracks(args.tracks)
    vi = video_info(args.video)
    check_frame_size(tracks.meta, vi.width, vi.height, args.video, args.tracks)    # naming the tracks file
    info = write_preview(args.video, tracks, rig, frames, curves, args.output, sheet=args.sheet, head=head,
                         compare=compare, options=PreviewOptions(frames=args.frames, size=args.size,
                                                                 contours=args.contours, landmarks=args.landmarks))
    n, dt = info["frames"], info["seconds"]
    print(f"keyshape preview: {n} frames in {dt:.1f} s ({n / dt:.1f} frames/s; the rig render alone "
          f"{info['rig_frames'] / max(info['render_cpu_seconds'], 1e-9):.1f} rig frames per CPU second, "
          f"{rig.n_vertices} vertices)"
          + (f" -> {args.output}" if args.output else "") + (f"; sheet {args.sheet}" if args.sheet else ""))
    return 0


def _check_outputs(output, sheet, sheet_frames: int = 12, size: int | None = None) -> None:
    from pathlib import Path

    from keyshape.base.errors import InputError

    if not output and not sheet:
        raise InputError("give -o OUT.mp4 and/or --sheet SHEET.jpg")
    if output and Path(output).suffix.lower() not in (".mp4", ".avi"):
        raise InputError("preview output must end in .mp4 or .avi", output)
    if sheet and Path(sheet).suffix.lower() not in (".jpg", ".jpeg", ".png"):
        raise InputError("--sheet must end in .jpg or .png", sheet)
    if not 1 <= sheet_frames <= 1000:
        raise InputError(f"--sheet-frames {sheet_frames}: must be from 1 to 1000")
    if size is not None and not 16 <= size <= 8192:
        raise InputError(f"--size {size}: must be from 16 to 8192 pixels")


def write_preview(video, tracks, rig, frame_numbers, curves, output=None, *, sheet=None, head=None, compare=None,
                  options=None) -> dict:
    """Write the side-by-side preview (the footage with its contours | the shaded rig driven by
    ``curves`` [| the rig driven by a second set of curves]) to ``output`` (.mp4/.avi) and/or a contact
    ``sheet`` (.jpg/.png): what ``keyshape preview``, :func:`keyshape.api.preview` and ``keyshape batch`` run.

    Parameters
    ----------
    frame_numbers : the curves' frame numbers
    head : (n_frames, 3, 3) head rotations the rig is turned by (:func:`~keyshape.retarget.output.preview.head_rotations`)
    compare : ``(curves, head rotations or None)`` of a second set of curves for a third panel
    options : :class:`~keyshape.retarget.defaults.PreviewOptions` (the range, size, crop, contours, captions;
        default: its defaults)

    Returns ``{"frames", "rig_frames", "seconds", "render_cpu_seconds"}``.
    """
    import time
    from pathlib import Path

    import cv2
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_write
    from keyshape.base.formats.tracks import check_frame_size
    from keyshape.base.formats.video import VideoReader
    from keyshape.base.progress import Progress
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.retarget.output.preview import (RigRenderer, actor_panel, caption, face_crop, ordered_map, panel_row,
                                           parse_frames)
    from keyshape.retarget.defaults import PreviewOptions
    from keyshape.retarget.rig.model import default_landmarks, rig_landmarks

    o = options if options is not None else PreviewOptions()
    size, sheet_frames, threads, crop, contours, landmarks = o.size, o.sheet_frames, o.threads, o.crop, o.contours, \
        o.landmarks
    _check_outputs(output, sheet, sheet_frames, size)
    if crop not in ("face", "full"):
        raise InputError(f"crop {crop!r}: use face or full")
    spec, frames = o.frames, np.asarray(frame_numbers)
    curves = np.asarray(curves, dtype=np.float64)
    scheme = scheme_for_n_points(tracks.n_points)
    pos = {int(f): i for i, f in enumerate(tracks.frame)}
    rows = parse_frames(spec, frames)
    reader = VideoReader(video)
    check_frame_size(tracks.meta, reader.info.width, reader.info.height, video)
    h = size or reader.info.height
    box = None
    if crop == "face":
        trows = [pos[int(frames[r])] for r in rows if int(frames[r]) in pos]
        box = face_crop(tracks.points[trows], tracks.success[trows], (reader.info.width, reader.info.height))
    lm = None
    if contours or (contours is None and (landmarks or default_landmarks(rig.n_vertices, scheme.name))):
        lm = (rig_landmarks(rig, scheme.name, landmarks)[0], scheme)
    other, other_head = compare if compare is not None else (None, None)
    # fitted on every frame to render, each with its own turn, so that the triangles no frame shows are
    # left out of the drawing (cull_hidden: the backs of the eyeballs, the teeth behind closed lips)
    fit_curves = [curves[rows]] + ([other[rows]] if other is not None else [])
    fit_turns = None
    if head is not None or other_head is not None:
        still = np.broadcast_to(np.eye(3), (len(rows), 3, 3))
        fit_turns = np.concatenate([still if x is None else x[rows]
                                    for x in (head, other_head)[:len(fit_curves)]])
    renderer = RigRenderer(rig, size=(h, h), landmarks=lm, cull_hidden=True).fit(np.concatenate(fit_curves),
                                                                                 fit_turns)
    names = list(o.captions or [])
    fps = reader.info.fps or 30.0
    sheet_rows = set(rows[np.linspace(0, len(rows) - 1, min(sheet_frames, len(rows))).round().astype(int)]
                     .tolist()) if sheet else set()
    want = {int(frames[r]): r for r in rows}
    last = max(want)
    tiles, tile_captions = [], []
    t0 = time.perf_counter()
    t_render = 0.0
    n = n_rig = 0

    def frame(job):
        """Row ``r``'s output frame: the actor panel of video frame ``img`` beside the rig panels of
        ``curves`` (and the compared curves), captioned; and the CPU seconds of the rig panels alone."""
        img, k, r = job
        left = actor_panel(img, tracks.points[k] if k is not None else None, scheme,
                           bool(tracks.success[k]) if k is not None else False, h, box)
        t = time.thread_time()
        right = [renderer.render_curves(curves[r], None if head is None else head[r])]
        if other is not None:
            right.append(renderer.render_curves(other[r], None if other_head is None else other_head[r]))
        cpu = time.thread_time() - t
        panels = [left, *right]
        return panel_row([caption(p, t) if t else p for p, t in zip(panels, names + [""] * len(panels))]), cpu

    def jobs(wr, prog):
        """((frame, row), (image, tracks row, row)) for each frame to render, as the video is read
        (frames not rendered are counted here)."""
        nonlocal n
        for i, img in reader:
            if i > last:
                break
            r = want.get(i)
            if r is None or (wr is None and r not in sheet_rows):     # a sheet alone renders only its frames
                if r is not None:
                    n += 1
                    prog.update()
                continue
            yield (i, r), (img, pos.get(i), r)

    with _maybe_writer(output, fps) as wr:
        prog = Progress(len(rows), desc="keyshape preview")
        # whole frames are drawn on a few threads (fillPoly, resizing and numpy release the GIL), encoded
        # on another, in order
        for (i, r), (out, cpu), _ in ordered_map(frame, jobs(wr, prog), threads):
            t_render += cpu
            n_rig += 1 + (other is not None)
            if wr is not None:
                wr(out)
            if r in sheet_rows:
                tiles.append(out)
                tile_captions.append(f"frame {i}")
            n += 1
            prog.update()
        prog.close()
    if n < len(rows):
        raise InputError(f"the video ended after frame {reader.n_read - 1}; the curves go on to frame {last}",
                         video)
    if sheet:
        from keyshape.base.draw import contact_sheet
        img = contact_sheet(tiles, tile_captions, columns=3 if other is None else 2, tile_width=tiles[0].shape[1])
        ok, buf = cv2.imencode(Path(sheet).suffix.lower(), img,
                               [cv2.IMWRITE_JPEG_QUALITY, 85] if not str(sheet).lower().endswith(".png") else [])
        with atomic_write(sheet, "wb") as f:
            f.write(buf.tobytes())
    return {"frames": n, "rig_frames": n_rig, "seconds": time.perf_counter() - t0, "render_cpu_seconds": t_render}


class _maybe_writer:
    """Context manager: a frame sink writing a video at ``path`` (sized from the first frame), or None.

    Frames are encoded on a thread of their own (OpenCV's encoder releases the GIL), so the encoding
    overlaps the rendering; at most ``queue`` frames wait. An encoding error is raised in the caller,
    at its next frame or on leaving the block.
    """

    def __init__(self, path, fps, queue: int = 8):
        self.path, self.fps, self.size = path, fps, queue
        self.cm = self.wr = self.q = self.thread = self.error = None

    def __enter__(self):
        if self.path is None:
            return None
        import threading

        from keyshape.base.interrupts import Handoff, start_thread
        self.q = Handoff(self.size)         # Ctrl-C in a full queue's put cannot wedge it (interrupts)
        self.thread = threading.Thread(target=self._encode, name="keyshape-encode", daemon=True)
        start_thread(self.thread)
        return self._write

    def _encode(self):
        while (img := self.q.get()) is not None:
            if self.error is not None:
                continue                                   # drain: the caller stops at its next frame
            try:
                if self.wr is None:
                    from keyshape.base.formats.video import video_writer
                    self.cm = video_writer(self.path, self.fps, (img.shape[1], img.shape[0]))
                    self.wr = self.cm.__enter__()
                self.wr.write(img)
            except Exception as exc:  # noqa: BLE001 -- any failure is handed to the caller's thread
                self.error = exc

    def _write(self, img):
        if self.error is not None:
            raise self.error
        self.q.put(img)

    def __exit__(self, *exc):
        if self.thread is None:
            return False
        self.q.put(None)
        self.thread.join()
        failed = exc[0] is not None or self.error is not None
        if self.cm is not None:
            err = (type(self.error), self.error, self.error.__traceback__) if self.error is not None else exc
            self.cm.__exit__(*err) if failed else self.cm.__exit__(None, None, None)
        if self.error is not None and exc[0] is None:
            raise self.error
        return False
