"""``keyshape synth mocap``: a synthetic facial-mocap take on ICT-FaceKit with dense ground truth."""
from __future__ import annotations

from pathlib import Path

from keyshape.data_synth.face3d_cli import DEFAULT_FACEKIT


def register(subparsers) -> None:
    """Add ``keyshape synth mocap``."""
    p = subparsers.add_parser(
        "mocap", help="synthetic 3D marker take on ICT-FaceKit (C3D/TRC at 120 Hz + dense ground truth)",
        description="Writes OUT_DIR/take.c3d, take.trc (mm, with a 5-marker head jig, noise and gaps), "
                    "target_markers.json (label -> ICT vertex), rigid.txt (jig labels), masks.json "
                    "(lip and eyelid discontinuity regions) and truth.npz (weights, head motion, "
                    "dense vertices per frame in the head frame, cm).")
    p.add_argument("out_dir")
    p.add_argument("--facekit", default=str(DEFAULT_FACEKIT), help="ICT-FaceKit folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=360)
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder keyshape did not make (only its own files are replaced)")
    p.set_defaults(func=_synth_mocap)


def _synth_mocap(args) -> int:
    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_dir, check_output_dir
    from keyshape.base.formats.masks import write_masks
    from keyshape.data_synth.mocap import discontinuity_regions, load_facekit, synthesize, write_take
    from keyshape.retarget.mocap.masks import masks_from_regions

    if args.frames < 2:
        raise InputError(f"--frames {args.frames}: must be >= 2")
    out_dir = Path(args.out_dir)
    check_output_dir(out_dir)
    kit = load_facekit(args.facekit)
    perf = synthesize(kit, args.frames, rng=args.seed)
    face = perf.labels[:len(perf.marker_vertices)]
    with atomic_dir(out_dir, kind="synth mocap") as tmp:
        paths = write_take(tmp, kit, perf)
        write_masks(tmp / "masks.json", masks_from_regions(discontinuity_regions(kit, face)))
    paths = {k: out_dir / Path(v).relative_to(tmp) for k, v in paths.items()}
    print(f"{args.frames} frames at {perf.rate:g} Hz, {len(perf.labels)} markers "
          f"({len(face)} face + {len(perf.labels) - len(face)} jig) -> {args.out_dir}")
    for k, v in paths.items():
        print(f"  {k}: {v}")
    return 0
