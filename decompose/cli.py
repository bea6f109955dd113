"""Command-line registration for the decompose stage: ``keyshape select``, ``decompose``, ``compare``.

Argument parsing and files only: the work is :mod:`keyshape.decompose.api`'s, every default
:mod:`keyshape.decompose.defaults`'."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from keyshape.decompose import defaults as D
from keyshape.decompose.defaults import METHODS, SOLVERS


def register(subparsers) -> None:
    """Add this stage's subcommands to ``subparsers``."""
    p = subparsers.add_parser("select", help="choose key shapes (key frames) from one or more tracks files")
    p.add_argument("tracks", nargs="+",
                   help="tracks CSV (keyshape track, or truth.csv of keyshape synth video); several files of one "
                        "actor and one model give one key set for all of them")
    p.add_argument("-k", "--keys", dest="k", type=int, default=None,
                   help="key shapes per region (required but for --method hull2)")
    p.add_argument("--method", choices=METHODS, default=D.METHOD,
                   help=f"selector (default: {D.METHOD}, best in the project's measurements; spread is the paper's)")
    p.add_argument("--neutral-frame", default=D.NEUTRAL_FRAME, metavar="F|auto|mean",
                   help="what the weights are relative to: the actor's neutral, frame F or 'auto' (the most "
                        "relaxed frame, the default), or 'mean' (the take's mean shape, the paper's centring). "
                        "The actor's neutral is recorded in KEYS.json either way (for keyshape pose)")
    p.add_argument("--region", action="append", default=None,
                   help="mouth, eyes (with brows) or pupils; repeat for several (default: all the scheme has)")
    p.add_argument("--scheme", default=None, help="landmark scheme (default: the built-in one with as many points)")
    p.add_argument("--head-pose", choices=D.HEAD_POSES, default=D.HEAD_POSE,
                   help="how the head's motion is taken out of the shapes: 3d (the head's 3D pose, fitted to the "
                        "points rigid with the skull on a 3D face, is removed and the shapes are brought to the "
                        "front; rigid where the scheme has no 3D face), rigid (the tracker's pose, then "
                        "a 2D similarity on the rigid points, the eye corners) or tracker (the tracker's pose "
                        "alone); default " + D.HEAD_POSE + ". Recorded in KEYS.json; decompose, pose and retarget do the same")
    p.add_argument("-o", "--output", required=True, help="KEYS.json to write")
    p.add_argument("--sheet", default=None, help="also write a key-frame sheet, .png or .jpg (needs --video)")
    p.add_argument("--video", default=None, help="the video the tracks came from (for --sheet)")
    _partial_option(p)
    p.set_defaults(func=_select)

    p = subparsers.add_parser("decompose", help="per-frame weights of the key shapes (NNLS, eq. 4)")
    p.add_argument("tracks", help="tracks CSV")
    p.add_argument("--keys", required=True, help="KEYS.json from keyshape select")
    p.add_argument("--solver", choices=SOLVERS, default=D.SOLVER,
                   help=f"nnls (the paper's), lstsq (unconstrained), smooth (NNLS + temporal smoothness); "
                        f"default {D.SOLVER}")
    p.add_argument("--ridge", type=float, default=D.RIDGE,
                   help="shrink weights towards 0 against tracking noise: Tikhonov term, dimensionless "
                        f"(default {D.RIDGE:g}; 0 with --solver nnls is the paper's NNLS)")
    p.add_argument("--allow-foreign-keys", action="store_true",
                   help="use keys chosen from tracks of another tracker model (refused by default)")
    p.add_argument("-o", "--output", required=True, help="WEIGHTS.csv to write")
    _partial_option(p)
    p.set_defaults(func=_decompose)

    p = subparsers.add_parser("compare", help="reconstruction error against k per selector (paper Figure 6)")
    p.add_argument("tracks", help="tracks CSV")
    p.add_argument("--kmin", type=int, default=2, help="smallest k (default 2)")
    p.add_argument("--kmax", type=int, default=24, help="largest k (default 24)")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS), help="selectors to compare")
    p.add_argument("--region", action="append", default=None, help="regions (default: all the scheme has)")
    p.add_argument("-o", "--output", required=True, help="folder for errors.csv and errors.png")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder keyshape did not make (only its own files are replaced)")
    _partial_option(p)
    p.set_defaults(func=_compare)


def _partial_option(p) -> None:
    p.add_argument("--accept-partial", action="store_true",
                   help="read tracks an interrupted 'keyshape track' marked partial (NAME.partial.csv)")


def _load(args, path=None):
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.decompose.api import tracks_scheme

    path = args.tracks if path is None else path
    tracks = read_tracks(path, accept_partial=getattr(args, "accept_partial", False))
    return tracks, tracks_scheme(tracks, getattr(args, "scheme", None), path)


def _load_many(args):
    """Several tracks files of one actor: the tracks of each, and the KEYS.json ``source`` entry."""
    from keyshape.base.errors import InputError

    loaded = [_load(args, p) for p in args.tracks]
    tracks, scheme = loaded[0]
    models = {t.meta.get("model") for t, _ in loaded}
    if len(models) > 1:
        which = ", ".join(f"{p}: {t.meta.get('model', 'unknown')}" for p, (t, _) in zip(args.tracks, loaded))
        raise InputError(f"the tracks come from different tracker models ({which}); one key set needs "
                         "one actor's model")
    if len({t.n_points for t, _ in loaded}) > 1:
        raise InputError("the tracks files have different point counts", args.tracks[1])
    source = {"scheme": scheme.name, "tracks": [str(p) for p in args.tracks]}
    if tracks.meta.get("model"):
        source["model"] = tracks.meta["model"]
    return [t for t, _ in loaded], source


def _select(args) -> int:
    from keyshape.base.errors import InputError
    from keyshape.base.formats.keys import write_keys
    from keyshape.decompose.regions import stable_pose

    # everything that can be checked before any work or any output
    if args.k is None and args.method != "hull2":
        raise InputError(f"-k is required for --method {args.method}")
    if args.k is not None and args.k < 1:
        raise InputError(f"-k {args.k}: need at least 1 key shape per region")
    if args.sheet and not args.video:
        raise InputError("--sheet needs --video (the video the tracks came from)")
    if args.sheet and len(args.tracks) > 1:
        raise InputError("--sheet works with one tracks file (and its --video)")
    if args.sheet and Path(args.sheet).suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise InputError(f"--sheet {args.sheet}: use a .png or .jpg file name")
    from keyshape.decompose import api as A

    nf = A.parse_neutral_frame(args.neutral_frame)
    if nf not in (None, "auto") and len(args.tracks) > 1:
        raise InputError("--neutral-frame F is ambiguous with several tracks files: use auto")
    loaded, source = _load_many(args)
    tracks = loaded[0]
    if args.video:
        from keyshape.base.formats.video import video_info
        info = video_info(args.video)
        last = int(tracks.frame.max())
        if info.n_frames > 0 and last >= info.n_frames:
            raise InputError(f"the tracks go to frame {last} but the video has {info.n_frames} frames: "
                             "is this the video the tracks came from?", args.video)
        from keyshape.base.formats.tracks import check_frame_size
        check_frame_size(tracks.meta, info.width, info.height, args.video, args.tracks[0])
    scheme, chosen, head_pose = A.select_keys(
        loaded if len(loaded) > 1 else tracks, args.k, args.method, args.region, args.scheme,
        source=args.tracks[0], progress=True, head=args.head_pose, neutral_frame=nf)
    # the sheet is made (video decoded) before any output is written: a failure writes nothing
    sheet = encode_sheet(args.sheet, args.video, tracks, scheme, chosen, stable_pose(tracks, head_pose)) \
        if args.sheet else None
    write_keys(args.output, scheme.name, scheme.n_points, chosen, source, head_pose)
    for rk in chosen:
        dropped = f" ({args.k - len(rk.keys)} near-duplicate keys dropped)" if args.k and len(rk.keys) < args.k \
            else ""
        print(f"{rk.region}: {len(rk.keys)} keys ({rk.method}) at frames {', '.join(map(str, rk.frames))}; "
              f"neutral frame {rk.rest_frame}{dropped}")
    if sheet is not None:
        from keyshape.base.files import atomic_write

        with atomic_write(args.sheet, "wb") as f:
            f.write(sheet)
        print(f"sheet: {args.sheet}")
    print(f"wrote {args.output}")
    return 0


def encode_sheet(path, video, tracks, scheme, chosen, poses=None) -> bytes:
    """The key-frame sheet of ``chosen``, encoded for ``path``'s suffix (.png or .jpg); ``poses``: the
    head poses the keys' frame goes with (default the tracks' own)."""
    import cv2

    from keyshape.base.errors import InputError
    from keyshape.decompose.sheet import key_sheet

    suffix = Path(path).suffix.lower()
    if suffix not in (".png", ".jpg", ".jpeg"):
        raise InputError(f"--sheet {path}: use a .png or .jpg file name")
    img = key_sheet(video, tracks, scheme, chosen, poses=poses)
    ok, buf = cv2.imencode(suffix, img, [cv2.IMWRITE_JPEG_QUALITY, 88] if suffix != ".png" else [])
    if not ok:
        raise InputError("OpenCV could not encode the sheet", path)
    return buf.tobytes()


def write_sheet(path, video, tracks, scheme, chosen, poses=None) -> None:
    """Write the key-frame sheet of ``chosen`` (.png or .jpg) atomically."""
    from keyshape.base.files import atomic_write

    data = encode_sheet(path, video, tracks, scheme, chosen, poses)
    with atomic_write(path, "wb") as f:
        f.write(data)


def _decompose(args) -> int:
    from keyshape.base.errors import InputError
    from keyshape.base.formats.keys import read_keys
    from keyshape.base.formats.weights import write_weights
    from keyshape.decompose.api import decompose_keys

    if not (np.isfinite(args.ridge) and 0 <= args.ridge <= 1e6):      # before any work (decompose_keys checks it too)
        raise InputError(f"--ridge {args.ridge}: must be a finite number from 0 to 1e6")
    tracks, scheme = _load(args)
    scheme_name, n_points, regions = read_keys(args.keys)
    from keyshape.base.formats.keys import check_keys_model, read_keys_head_pose
    head = read_keys_head_pose(args.keys)
    check_keys_model(args.keys, tracks.meta.get("model"), args.allow_foreign_keys)
    if n_points != tracks.n_points:
        raise InputError(f"key shapes are for {n_points} points ({scheme_name}), the tracks have "
                         f"{tracks.n_points}", args.keys)
    names, w = decompose_keys(tracks, regions, args.solver, ridge=args.ridge, source=args.tracks, head_pose=head)
    write_weights(args.output, tracks.frame, names, w, ~tracks.success, fps=tracks.fps)
    n_fail = int((~tracks.success).sum())
    print(f"wrote {args.output}: {tracks.n_frames} frames x {len(names)} weights ({args.solver})"
          + (f"; {n_fail} failed frames interpolated (column 'interpolated')" if n_fail else ""))
    return 0


def _compare(args) -> int:
    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_dir, check_output_dir
    from keyshape.base.progress import Progress
    from keyshape.decompose.compare import compare, plot_errors, write_errors

    if not 1 <= args.kmin <= args.kmax:
        raise InputError(f"--kmin {args.kmin} --kmax {args.kmax}: need 1 <= kmin <= kmax")
    check_output_dir(args.output)
    tracks, scheme = _load(args)
    with Progress(desc="keyshape compare", unit="rows") as bar:
        rows = compare(tracks, scheme, methods=args.methods, regions=args.region, kmin=args.kmin, kmax=args.kmax,
                       amplitude=2.0, rng=0, progress=bar)
    out = Path(args.output)
    with atomic_dir(out, kind="compare") as tmp:
        write_errors(tmp / "errors.csv", rows)
        plot_errors(tmp / "errors.png", rows)
    print(f"wrote {out / 'errors.csv'} and {out / 'errors.png'}")
    return 0
