"""``keyshape synth face3d``: footage of a shaded 3D head (ICT-FaceKit) with rig, head-pose and gaze truth."""
from __future__ import annotations

import time
from pathlib import Path

DEFAULT_FACEKIT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict-facekit"


def register(subparsers) -> None:
    """Add ``face3d`` under ``keyshape synth``."""
    p = subparsers.add_parser(
        "face3d", help="footage of a shaded 3D ICT-FaceKit head with known curves, head pose and gaze",
        description="Write video.mp4, truth.csv (contours48 landmarks per frame), curves.csv (the rig's "
                    "curves, as retarget --poses --rig writes them), head.csv (head yaw/pitch/roll in "
                    "degrees, translation in cm, eye yaw/pitch per eye), labels/ (training frames as .pts) "
                    "and truth.json (camera, identity, conventions) into OUT_DIR.")
    p.add_argument("out_dir", metavar="OUT_DIR", help="output folder (created)")
    p.add_argument("--rig", default=str(DEFAULT_FACEKIT),
                   help="ICT-FaceKit folder (default ../shared/data/ict-facekit)")
    from keyshape.data_synth.video_cli import add_footage_options

    add_footage_options(p, frames=300)
    p.add_argument("--identity", choices=("mixed", "generic"), default="mixed",
                   help="mixed: a seeded mix of ICT-FaceKit's identities, rescaled; generic: its neutral (default mixed)")
    p.set_defaults(func=run)


def run(args) -> int:
    from keyshape.base.files import atomic_dir, check_output, check_output_dir
    from keyshape.data_synth.face3d import check_facekit, synthesize
    from keyshape.data_synth.video import _check_args, parse_size

    size = parse_size(args.size)
    _check_args(args.frames, args.seed, size, args.fps, args.labels)
    check_facekit(args.rig)
    out_dir = Path(args.out_dir)
    check_output_dir(out_dir, args.overwrite)
    if args.preview:
        check_output(args.preview)
    t0 = time.perf_counter()
    with atomic_dir(out_dir, args.overwrite) as tmp:
        preview = args.preview
        if preview and Path(preview).resolve().parent == out_dir.resolve():
            preview = tmp / Path(args.preview).name
        out = synthesize(tmp, args.rig, frames=args.frames, seed=args.seed, size=size, fps=args.fps,
                         labels=args.labels, identity=args.identity, preview=preview, verbose=True)
    out = {k: (out_dir / Path(v).relative_to(tmp) if Path(v).is_relative_to(tmp) else Path(v))
           for k, v in out.items()}
    dt = time.perf_counter() - t0
    print(f"keyshape synth face3d: {args.frames} frames in {dt:.1f} s ({1000 * dt / args.frames:.1f} ms/frame)")
    for name, path in out.items():
        print(f"  {name:11s} {path}")
    return 0
