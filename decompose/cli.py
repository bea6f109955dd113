"""Command-line registration for the decompose stage: ``keyshape select``, ``decompose``, ``compare``."""
from __future__ import annotations

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
    p.set_defaults(func=_compare)


def _load(args):
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.schemes import load_scheme, scheme_for_n_points
    from keyshape.base.errors import InputError

    tracks = read_tracks(args.tracks)
    scheme = load_scheme(args.scheme) if getattr(args, "scheme", None) else scheme_for_n_points(tracks.n_points)
    if scheme.n_points != tracks.n_points:
        raise InputError(f"scheme {scheme.name!r} has {scheme.n_points} points, the tracks {tracks.n_points}",
                         args.tracks)
    return tracks, scheme


def _select(args) -> int:
    from pathlib import Path

    from keyshape.base.errors import InputError
    from keyshape.base.formats.keys import write_keys
    from keyshape.decompose.regions import available_regions, model_shapes, select_region

    tracks, scheme = _load(args)
    if args.k is None and args.method != "hull2":
        raise InputError(f"-k is required for --method {args.method}")
    if args.sheet and not args.video:
        raise InputError("--sheet needs --video (the video the tracks came from)")
    shapes = model_shapes(tracks, args.tracks)
    regions = args.region or available_regions(scheme)
    try:
        chosen = [select_region(tracks, scheme, r, args.k, args.method, rng=args.seed, shapes=shapes)
                  for r in regions]
    except InputError as exc:
        raise InputError(str(exc), args.tracks) from None
    write_keys(args.output, scheme.name, scheme.n_points, chosen)
    for rk in chosen:
        print(f"{rk.region}: {len(rk.keys)} keys ({rk.method}) at frames {', '.join(map(str, rk.frames))}")
    if args.sheet:
        from keyshape.decompose.sheet import key_sheet
        from keyshape.base.files import atomic_write
        import cv2

        suffix = Path(args.sheet).suffix.lower()
        if suffix not in (".png", ".jpg", ".jpeg"):
            raise InputError(f"--sheet {args.sheet}: use a .png or .jpg file name")
        img = key_sheet(args.video, tracks, scheme, chosen)
        ok, buf = cv2.imencode(suffix, img, [cv2.IMWRITE_JPEG_QUALITY, 88] if suffix != ".png" else [])
        with atomic_write(args.sheet, "wb") as f:
            f.write(buf.tobytes())
        print(f"sheet: {args.sheet}")
    print(f"wrote {args.output}")
    return 0


def _decompose(args) -> int:
    import numpy as np

    from keyshape.base.errors import InputError
    from keyshape.base.formats.keys import read_keys, write_weights
    from keyshape.decompose.regions import decompose_region, model_shapes

    tracks, scheme = _load(args)
    scheme_name, n_points, regions = read_keys(args.keys)
    if n_points != tracks.n_points:
        raise InputError(f"key shapes are for {n_points} points ({scheme_name}), the tracks have "
                         f"{tracks.n_points}", args.keys)
    shapes = model_shapes(tracks, args.tracks)
    names, cols = [], []
    for rk in regions:
        cols.append(decompose_region(tracks, rk, args.solver, args.smooth_lambda, shapes=shapes, ridge=args.ridge))
        names += rk.names
    w = np.concatenate(cols, axis=1)
    write_weights(args.output, tracks.frame, names, w, ~tracks.success)
    n_fail = int((~tracks.success).sum())
    print(f"wrote {args.output}: {tracks.n_frames} frames x {len(names)} weights ({args.solver})"
          + (f"; {n_fail} failed frames interpolated (column 'interpolated')" if n_fail else ""))
    return 0


def _compare(args) -> int:
    from pathlib import Path

    from keyshape.decompose.compare import compare, plot_errors, write_errors

    tracks, scheme = _load(args)
    rows = compare(tracks, scheme, methods=args.methods, regions=args.region, kmin=args.kmin, kmax=args.kmax,
                   amplitude=args.amplitude, rng=args.seed,
                   progress=lambda r, m: print(f"  {r}: {m} done", flush=True))
    out = Path(args.output)
    write_errors(out / "errors.csv", rows)
    plot_errors(out / "errors.png", rows)
    print(f"wrote {out / 'errors.csv'} and {out / 'errors.png'}")
    return 0
