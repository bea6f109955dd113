"""Command-line registration for the decompose stage: ``keyshape select``, ``decompose``, ``compare``."""
from __future__ import annotations

from pathlib import Path

import numpy as np

METHODS = ("spread", "kmeans2", "kmeans3", "hull2", "random", "greedy")
SOLVERS = ("nnls", "lstsq", "smooth")


def register(subparsers) -> None:
    """Add this stage's subcommands to ``subparsers``."""
    p = subparsers.add_parser("select", help="choose key shapes (key frames) from a tracks file")
    p.add_argument("tracks", help="tracks CSV (keyshape track, or truth.csv of keyshape synth video)")
    p.add_argument("-k", "--keys", dest="k", type=int, default=None,
                   help="key shapes per region (required but for --method hull2)")
    p.add_argument("--method", choices=METHODS, default="spread", help="selector (default: spread, the paper's)")
    p.add_argument("--region", action="append", default=None,
                   help="mouth, eyes (with brows) or pupils; repeat for several (default: all the scheme has)")
    p.add_argument("--scheme", default=None, help="landmark scheme (default: the built-in one with as many points)")
    p.add_argument("--seed", type=int, default=0, help="seed of kmeans/random/greedy (default 0)")
    p.add_argument("-o", "--output", required=True, help="KEYS.json to write")
    p.add_argument("--sheet", default=None, help="also write a key-frame sheet, .png or .jpg (needs --video)")
    p.add_argument("--video", default=None, help="the video the tracks came from (for --sheet)")
    _partial_option(p)
    p.set_defaults(func=_select)

    p = subparsers.add_parser("decompose", help="per-frame weights of the key shapes (NNLS, eq. 4)")
    p.add_argument("tracks", help="tracks CSV")
    p.add_argument("--keys", required=True, help="KEYS.json from keyshape select")
    p.add_argument("--solver", choices=SOLVERS, default="nnls",
                   help="nnls (default), lstsq (unconstrained), smooth (NNLS + temporal smoothness)")
    p.add_argument("--smooth-lambda", type=float, default=0.1,
                   help="weight of the frame-to-frame change penalty for --solver smooth (default 0.1)")
    p.add_argument("--ridge", type=float, default=0.0,
                   help="shrink weights towards 0 against tracking noise: Tikhonov term, dimensionless "
                        "(0 = the paper's NNLS, the default; 0.01-0.1 on noisy tracks)")
    p.add_argument("-o", "--output", required=True, help="WEIGHTS.csv to write")
    _partial_option(p)
    p.set_defaults(func=_decompose)

    p = subparsers.add_parser("compare", help="reconstruction error against k per selector (paper Figure 6)")
    p.add_argument("tracks", help="tracks CSV")
    p.add_argument("--kmin", type=int, default=2, help="smallest k (default 2)")
    p.add_argument("--kmax", type=int, default=24, help="largest k (default 24)")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS), help="selectors to compare")
    p.add_argument("--region", action="append", default=None, help="regions (default: all the scheme has)")
    p.add_argument("--amplitude", type=float, default=2.0,
                   help="target-domain check: amplitude (px) of the smooth field displacing the keys (default 2)")
    p.add_argument("--scheme", default=None, help="landmark scheme (default: by number of points)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--output", required=True, help="folder for errors.csv and errors.png")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder keyshape did not make (only its own files are replaced)")
    _partial_option(p)
    p.set_defaults(func=_compare)


def _partial_option(p) -> None:
    p.add_argument("--accept-partial", action="store_true",
                   help="read tracks an interrupted 'keyshape track' marked partial (NAME.partial.csv)")


def _load(args):
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.decompose.api import tracks_scheme

    tracks = read_tracks(args.tracks, accept_partial=getattr(args, "accept_partial", False))
    return tracks, tracks_scheme(tracks, getattr(args, "scheme", None), args.tracks)


def _select(args) -> int:
    from keyshape.base.errors import InputError
    from keyshape.base.formats.keys import write_keys
    from keyshape.base.files import check_outputs
    from keyshape.decompose.api import select_keys

    # everything that can be checked before any work or any output
    if args.k is None and args.method != "hull2":
        raise InputError(f"-k is required for --method {args.method}")
    if args.k is not None and args.k < 1:
        raise InputError(f"-k {args.k}: need at least 1 key shape per region")
    if args.sheet and not args.video:
        raise InputError("--sheet needs --video (the video the tracks came from)")
    if args.sheet and Path(args.sheet).suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise InputError(f"--sheet {args.sheet}: use a .png or .jpg file name")
    check_outputs([args.output, args.sheet], inputs=[args.tracks, args.video])
    tracks, _ = _load(args)
    if args.video:
        from keyshape.base.formats.video import video_info
        info = video_info(args.video)
        last = int(tracks.frame.max())
        if info.n_frames > 0 and last >= info.n_frames:
            raise InputError(f"the tracks go to frame {last} but the video has {info.n_frames} frames: "
                             "is this the video the tracks came from?", args.video)
    scheme, chosen = select_keys(tracks, args.k, args.method, args.region, args.scheme, args.seed, args.tracks,
                                 progress=True)
    # the sheet is made (video decoded) before any output is written: a failure writes nothing
    sheet = encode_sheet(args.sheet, args.video, tracks, scheme, chosen) if args.sheet else None
    write_keys(args.output, scheme.name, scheme.n_points, chosen)
    for rk in chosen:
        print(f"{rk.region}: {len(rk.keys)} keys ({rk.method}) at frames {', '.join(map(str, rk.frames))}")
    if sheet is not None:
        from keyshape.base.files import atomic_write

        with atomic_write(args.sheet, "wb") as f:
            f.write(sheet)
        print(f"sheet: {args.sheet}")
    print(f"wrote {args.output}")
    return 0


def encode_sheet(path, video, tracks, scheme, chosen) -> bytes:
    """The key-frame sheet of ``chosen``, encoded for ``path``'s suffix (.png or .jpg)."""
    import cv2

    from keyshape.base.errors import InputError
    from keyshape.decompose.sheet import key_sheet

    suffix = Path(path).suffix.lower()
    if suffix not in (".png", ".jpg", ".jpeg"):
        raise InputError(f"--sheet {path}: use a .png or .jpg file name")
    img = key_sheet(video, tracks, scheme, chosen)
    ok, buf = cv2.imencode(suffix, img, [cv2.IMWRITE_JPEG_QUALITY, 88] if suffix != ".png" else [])
    if not ok:
        raise InputError("OpenCV could not encode the sheet", path)
    return buf.tobytes()


def write_sheet(path, video, tracks, scheme, chosen) -> None:
    """Write the key-frame sheet of ``chosen`` (.png or .jpg) atomically."""
    from keyshape.base.files import atomic_write

    data = encode_sheet(path, video, tracks, scheme, chosen)
    with atomic_write(path, "wb") as f:
        f.write(data)


def _decompose(args) -> int:
    from keyshape.base.errors import InputError
    from keyshape.base.formats.keys import read_keys
    from keyshape.base.formats.weights import write_weights
    from keyshape.base.files import check_outputs
    from keyshape.decompose.api import decompose_keys

    for name, v in (("--smooth-lambda", args.smooth_lambda), ("--ridge", args.ridge)):
        if not (np.isfinite(v) and 0 <= v <= 1e6):
            raise InputError(f"{name} {v}: must be a finite number from 0 to 1e6")
    check_outputs([args.output], inputs=[args.tracks, args.keys])
    tracks, scheme = _load(args)
    scheme_name, n_points, regions = read_keys(args.keys)
    if n_points != tracks.n_points:
        raise InputError(f"key shapes are for {n_points} points ({scheme_name}), the tracks have "
                         f"{tracks.n_points}", args.keys)
    names, w = decompose_keys(tracks, regions, args.solver, args.smooth_lambda, args.ridge, args.tracks)
    write_weights(args.output, tracks.frame, names, w, ~tracks.success)
    n_fail = int((~tracks.success).sum())
    print(f"wrote {args.output}: {tracks.n_frames} frames x {len(names)} weights ({args.solver})"
          + (f"; {n_fail} failed frames interpolated (column 'interpolated')" if n_fail else ""))
    return 0


def _compare(args) -> int:
    from pathlib import Path

    import math

    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_dir, check_output_dir
    from keyshape.decompose.compare import compare, plot_errors, write_errors

    if not 1 <= args.kmin <= args.kmax:
        raise InputError(f"--kmin {args.kmin} --kmax {args.kmax}: need 1 <= kmin <= kmax")
    if not (math.isfinite(args.amplitude) and args.amplitude >= 0):
        raise InputError(f"--amplitude {args.amplitude}: must be a finite number >= 0")
    check_output_dir(args.output, args.overwrite, inputs=[args.tracks])
    tracks, scheme = _load(args)
    rows = compare(tracks, scheme, methods=args.methods, regions=args.region, kmin=args.kmin, kmax=args.kmax,
                   amplitude=args.amplitude, rng=args.seed,
                   progress=lambda r, m: print(f"  {r}: {m} done", flush=True))
    out = Path(args.output)
    with atomic_dir(out, args.overwrite, inputs=[args.tracks]) as tmp:
        write_errors(tmp / "errors.csv", rows)
        plot_errors(tmp / "errors.png", rows)
    print(f"wrote {out / 'errors.csv'} and {out / 'errors.png'}")
    return 0
