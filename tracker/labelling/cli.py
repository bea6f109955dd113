"""``keyshape label``: choose frames to label, pre-fill their points, correct them in a browser."""
from __future__ import annotations

import argparse

from keyshape.base import options


def register(subparsers) -> None:
    """Add ``keyshape label`` to ``subparsers``."""
    p = subparsers.add_parser(
        "label", help="choose frames of a video to label, pre-fill them (dlib), correct them in a browser",
        description="Choose COUNT frames covering the performance's variety (sharp, never near-duplicates), "
                    "save them under DIR/frames/, pre-fill their points with dlib's 68-point landmarker "
                    "(optional extra: pip install \"keyshape[label]\") converted to the scheme, write "
                    "DIR/NNNNNN.pts (NNNNNN = zero-based frame index) and DIR/contact_sheet.png. With --serve, "
                    "open a local page (127.0.0.1 only) to drag the points and save them. Running it again on "
                    "the same DIR keeps the chosen frames and the points already saved.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("video", help="the performance video")
    p.add_argument("--count", "-k", type=int, default=12, help="frames to label")
    p.add_argument("-o", "--out", required=True, help="label folder to make (or resume)")
    p.add_argument("--scheme", default="contours48",
                   help="landmark scheme: contours48 (labelled with its 5 nose points: contours48+nose), ibug68 "
                        "or a JSON file")
    p.add_argument("--no-prefill", action="store_true",
                   help="start from a generic face shape instead of dlib's points")
    p.add_argument("--frames", type=_frame_list, default=None,
                   help="label exactly these zero-based frames (comma-separated) instead of choosing; on an "
                        "existing folder, add them to it")
    p.add_argument("--more", type=int, default=None, metavar="N",
                   help="active labelling: add to the existing folder DIR the N frames that the track "
                        "--tracks explains worst (lost frames, then lowest confidence)")
    p.add_argument("--tracks", default=None, metavar="TRACKS.csv",
                   help="with --more: the tracks CSV of a first `keyshape track` of this video")
    p.add_argument("--serve", action="store_true", help="start the correction page after preparing")
    p.add_argument("--port", type=options.port, default=8765, help="port of the correction page (0: any free port)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_run)


def _frame_list(text: str) -> list[int]:
    try:
        return [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated frame numbers, got {text!r}") from None


def _worst_frames(args) -> list[int]:
    from pathlib import Path  # noqa: PLC0415

    from keyshape.base.errors import InputError  # noqa: PLC0415
    from keyshape.base.formats.tracks import read_tracks  # noqa: PLC0415
    from keyshape.tracker.labelling.frames import worst_explained  # noqa: PLC0415
    from keyshape.base.formats.labels import SESSION_FILE, read_session  # noqa: PLC0415

    if args.more < 1:
        raise InputError(f"--more must be at least 1, got {args.more}")
    if args.tracks is None:
        raise InputError("--more needs --tracks TRACKS.csv (a first `keyshape track` of this video)")
    if not (Path(args.out) / SESSION_FILE).is_file():
        raise InputError("--more adds frames to an existing label folder: run `keyshape label` first", Path(args.out))
    have = read_session(Path(args.out))["frames"]
    tr = read_tracks(args.tracks)
    add = worst_explained(tr.confidence, tr.success, args.more, exclude=have, frames=tr.frame)
    if not len(add):
        raise InputError("no frame left to add (all within the minimum gap of labelled ones)", Path(args.tracks))
    print(f"adding the {len(add)} frames the track explains worst: {', '.join(map(str, add))}")
    return [int(f) for f in add]


def _run(args) -> int:
    from keyshape.tracker.labelling.prepare import prepare_label_folder, write_contact_sheet  # noqa: PLC0415

    if args.more is not None:
        args.frames = _worst_frames(args)
    session = prepare_label_folder(args.video, args.out, args.count, args.scheme,
                                   use_prefill=not args.no_prefill, quiet=args.quiet,
                                   frames=args.frames)
    frames = session["frames"]
    print(f"{len(frames)} frames in {args.out}: {', '.join(map(str, frames))}")
    if session.get("no_face"):
        print(f"no face found by dlib in frames {session['no_face']}: they start from a generic shape")
    print(f"check {args.out}/contact_sheet.png")
    if args.serve:
        from keyshape.tracker.labelling.server import LabelServer  # noqa: PLC0415
        from keyshape.base.schemes import load_scheme  # noqa: PLC0415
        from keyshape.base.localserver import listen, serve_until_stopped  # noqa: PLC0415

        server = listen(lambda: LabelServer(args.out, args.port), args.port)
        print(f"correct the points at {server.url} (Ctrl-C to stop)", flush=True)
        try:
            serve_until_stopped(server)
        finally:
            write_contact_sheet(server.folder, frames, load_scheme(session["scheme"]))
            print(f"contact sheet redrawn: {args.out}/contact_sheet.png")
    return 0
