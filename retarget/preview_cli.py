"""``keyshape preview``: a take's footage with its contours beside the shaded rig driven by its curves."""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    """Add ``preview`` to ``subparsers``."""
    p = subparsers.add_parser(
        "preview", help="side-by-side video of a take: footage with contours | the shaded rig (and a contact sheet)",
        description="Render the footage with its tracked contours beside the rig driven by the take's curves "
                    "(a curves CSV from 'keyshape retarget ... --poses ... -o curves.csv', or key weights with "
                    "--poses), with a progress bar.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("video", help="the take's video")
    p.add_argument("--tracks", required=True, help="the take's tracks CSV (contours drawn on the footage)")
    p.add_argument("--curves", help="rig curves CSV (frame,<rig shape>,...)")
    p.add_argument("--weights", help="key weights CSV (keyshape decompose), with --poses")
    p.add_argument("--poses", help="POSES.json (keyshape pose), with --weights")
    p.add_argument("--rig", nargs="+", required=True, metavar="DIR|FILE", help="the rig (folder of shape OBJs)")
    p.add_argument("--neutral", default=None, help="the rig's neutral OBJ (default: found in the folder)")
    p.add_argument("--frames", default=None, metavar="A:B", help="frame range, B exclusive (default: all)")
    p.add_argument("--size", type=int, default=None,
                   help="height of the output in pixels (default: the video's height)")
    p.add_argument("--sheet", default=None, help="also write a contact sheet (actor | character), .jpg or .png")
    p.add_argument("--sheet-frames", type=int, default=12, help="frames in the contact sheet, spread over the range")
    p.add_argument("--threads", type=int, default=None,
                   help="rendering threads (default: one per core, at most 4)")
    p.add_argument("-o", "--output", default=None, help="OUT.mp4 / .avi (optional with --sheet)")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.formats.weights import read_weights
    from keyshape.retarget.rig import load_rig

    _check_outputs(args.output, args.sheet, args.sheet_frames, args.size)
    if bool(args.curves) == bool(args.weights or args.poses):
        raise InputError("give either --curves CURVES.csv or --weights WEIGHTS.csv with --poses POSES.json")
    rig = load_rig(args.rig if len(args.rig) > 1 else args.rig[0], args.neutral)
    if args.curves:
        frames, names, c, _ = read_weights(args.curves)
        missing = [n for n in rig.names if n not in names]
        if missing and len(missing) == rig.n_shapes:
            raise InputError("no column names a rig shape", args.curves)
        curves = np.zeros((len(frames), rig.n_shapes))
        for j, n in enumerate(rig.names):
            if n in names:
                curves[:, j] = c[:, names.index(n)]
    else:
        if not (args.weights and args.poses):
            raise InputError("--weights and --poses go together")
        from keyshape.base.formats.poses import read_poses
        from keyshape.retarget.api import rig_curves
        frames, cols, w, _ = read_weights(args.weights)
        curves = rig_curves(w, cols, read_poses(args.poses, rig.names), rig, args.poses)
    tracks = read_tracks(args.tracks)
    info = write_preview(args.video, tracks, rig, frames, curves, args.output, sheet=args.sheet, frames=args.frames,
                         size=args.size, sheet_frames=args.sheet_frames, threads=args.threads,
                         tracks_source=args.tracks)
    n, dt = info["frames"], info["seconds"]
    print(f"keyshape preview: {n} frames in {dt:.1f} s ({n / dt:.1f} frames/s; the rig render alone "
          f"{n / max(info['render_cpu_seconds'], 1e-9):.1f} frames per CPU second, {rig.n_vertices} vertices)"
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


def write_preview(video, tracks, rig, frame_numbers, curves, output=None, *, sheet=None, frames: str | None = None,
                  size: int | None = None, sheet_frames: int = 12, threads: int | None = None,
                  tracks_source=None) -> dict:
    """Write the side-by-side preview (the footage with its contours | the shaded rig driven by
    ``curves``) to ``output`` (.mp4/.avi) and/or a contact ``sheet`` (.jpg/.png): what ``keyshape
    preview``, :func:`keyshape.api.preview` and ``keyshape batch`` run.

    ``frame_numbers``: the curves' frame numbers; ``frames``: the range to render, ``"A:B"`` (B
    exclusive; default all). Returns ``{"frames", "seconds", "render_cpu_seconds"}``.
    """
    import time
    from pathlib import Path

    import cv2
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_write
    from keyshape.base.formats.video import VideoReader
    from keyshape.base.progress import Progress
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.retarget.preview import RigRenderer, actor_panel, ordered_map, parse_frames
    from keyshape.retarget.render import side_by_side

    _check_outputs(output, sheet, sheet_frames, size)
    spec, frames = frames, np.asarray(frame_numbers)
    curves = np.asarray(curves, dtype=np.float64)
    scheme = scheme_for_n_points(tracks.n_points)
    pos = {int(f): i for i, f in enumerate(tracks.frame)}
    rows = parse_frames(spec, frames)
    reader = VideoReader(video)
    from keyshape.base.formats.tracks import check_frame_size
    check_frame_size(tracks.meta, reader.info.width, reader.info.height, video, tracks_source)
    h = size or reader.info.height
    renderer = RigRenderer(rig, size=(h, h)).fit(curves[rows])
    fps = reader.info.fps or 30.0
    sheet_rows = set(rows[np.linspace(0, len(rows) - 1, min(sheet_frames, len(rows))).round().astype(int)]
                     .tolist()) if sheet else set()
    want = {int(frames[r]): r for r in rows}
    last = max(want)
    tiles, captions = [], []
    t0 = time.perf_counter()
    t_render = 0.0
    n = 0

    def jobs(wr, prog):
        """(frame, row, actor panel) for each frame to render, as the video is read (frames not
        rendered are counted here)."""
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
            k = pos.get(i)
            left = actor_panel(img, tracks.points[k] if k is not None else None, scheme,
                               bool(tracks.success[k]) if k is not None else False, h)
            yield (i, r, left), curves[r]

    with _maybe_writer(output, fps) as wr:
        prog = Progress(len(rows), desc="keyshape preview")
        # the rig is rendered on a few threads (fillPoly and numpy release the GIL), written in order
        for (i, r, left), right, cpu in ordered_map(renderer.render_curves, jobs(wr, prog), threads):
            t_render += cpu
            out = side_by_side(left, right)
            if wr is not None:
                wr(out)
            if r in sheet_rows:
                tiles.append(out)
                captions.append(f"frame {i}")
            n += 1
            prog.update()
        prog.close()
    if n < len(rows):
        raise InputError(f"the video ended after frame {reader.n_read - 1}; the curves go on to frame {last}",
                         video)
    if sheet:
        from keyshape.base.draw import contact_sheet
        img = contact_sheet(tiles, captions, columns=3, tile_width=2 * h + 4)
        ok, buf = cv2.imencode(Path(sheet).suffix.lower(), img,
                               [cv2.IMWRITE_JPEG_QUALITY, 85] if not str(sheet).lower().endswith(".png") else [])
        with atomic_write(sheet, "wb") as f:
            f.write(buf.tobytes())
    return {"frames": n, "seconds": time.perf_counter() - t0, "render_cpu_seconds": t_render}


class _maybe_writer:
    """Context manager: a frame sink writing a video at ``path`` (sized from the first frame), or None."""

    def __init__(self, path, fps):
        self.path, self.fps, self.cm, self.wr = path, fps, None, None

    def __enter__(self):
        if self.path is None:
            return None
        return self._write

    def _write(self, img):
        if self.wr is None:
            from keyshape.base.formats.video import video_writer
            self.cm = video_writer(self.path, self.fps, (img.shape[1], img.shape[0]))
            self.wr = self.cm.__enter__()
        self.wr.write(img)

    def __exit__(self, *exc):
        if self.cm is not None:
            return self.cm.__exit__(*exc)
        return False
