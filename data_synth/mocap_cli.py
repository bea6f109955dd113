"""``keyshape synth mocap``: a synthetic facial-mocap take on ICT-FaceKit with dense ground truth."""
from __future__ import annotations

from pathlib import Path

DEFAULT_FACEKIT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict-facekit"


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
    p.add_argument("--rate", type=float, default=120.0)
    p.add_argument("--noise", type=float, default=0.2, help="marker noise, mm (standard deviation)")
    p.add_argument("--gaps", type=int, default=6, help="number of short gaps (2-9 frames)")
    p.add_argument("--long-gap", type=int, default=60, help="length of one long gap on a cheek marker (0: none)")
    p.add_argument("--head-degrees", type=float, default=10.0, help="head rotation amplitude")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder keyshape did not make (only its own files are replaced)")
    p.set_defaults(func=_synth_mocap)


def _synth_mocap(args) -> int:
    from keyshape.data_synth.mocap import discontinuity_regions, load_facekit, synthesize, write_take
    import math

    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_dir, check_output_dir
    from keyshape.base.formats.masks import write_masks
    from keyshape.retarget.mocap.masks import masks_from_regions

    if args.frames < 2 or not (math.isfinite(args.rate) and 0 < args.rate <= 10000):
        raise InputError("--frames must be >= 2 and --rate a finite number of Hz in (0, 10000]")
    for name, v in (("--noise", args.noise), ("--head-degrees", args.head_degrees)):
        if not (math.isfinite(v) and 0 <= v <= 1000):
            raise InputError(f"{name} {v}: must be a finite number from 0 to 1000")
    if args.gaps < 0 or args.long_gap < 0:
        raise InputError("--gaps and --long-gap must be >= 0")
    out_dir = Path(args.out_dir)
    check_output_dir(out_dir, args.overwrite)
    kit = load_facekit(args.facekit)
    perf = synthesize(kit, args.frames, args.rate, rng=args.seed, noise_mm=args.noise, n_gaps=args.gaps,
                      long_gap=args.long_gap, head_degrees=args.head_degrees)
    face = perf.labels[:len(perf.marker_vertices)]
    with atomic_dir(out_dir, args.overwrite, kind="synth mocap") as tmp:
        paths = write_take(tmp, kit, perf)
        write_masks(tmp / "masks.json", masks_from_regions(discontinuity_regions(kit, face)))
    paths = {k: out_dir / Path(v).relative_to(tmp) for k, v in paths.items()}
    print(f"{args.frames} frames at {args.rate:g} Hz, {len(perf.labels)} markers "
          f"({len(face)} face + {len(perf.labels) - len(face)} jig) -> {args.out_dir}")
    for k, v in paths.items():
        print(f"  {k}: {v}")
    return 0
