"""``keyshape synth face3d``: footage of a shaded 3D head (ICT-FaceKit) with rig, head-pose and gaze truth."""
from __future__ import annotations

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
    p.set_defaults(func=run)


def run(args) -> int:
    from keyshape.data_synth.face3d import check_facekit, synthesize
    from keyshape.data_synth.video_cli import run_footage

    return run_footage(args, "face3d", lambda tmp, size, preview: synthesize(
        tmp, args.rig, frames=args.frames, seed=args.seed, size=size, fps=args.fps, labels=args.labels,
        preview=preview, verbose=True), check=lambda: check_facekit(args.rig))
