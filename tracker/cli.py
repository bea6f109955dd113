"""Command-line registration for the tracker stage: ``keyshape scheme``, ``train`` and ``track``."""
from __future__ import annotations

import sys


def register(subparsers) -> None:
    """Add the tracker's subcommands to ``subparsers``."""
    p = subparsers.add_parser("scheme", help="print a landmark scheme (points, contours, regions)")
    p.add_argument("name", nargs="?", default="contours48", help="contours48, ibug68 or a scheme JSON file")
    p.set_defaults(func=_scheme)

    p = subparsers.add_parser("train", help="train a person-specific eigen-points tracking model from labelled frames",
                              description="Train the appearance model of section 3 (Covell's eigen-points) from a "
                                          "handful of labelled frames. Labels are iBUG .pts files named by "
                                          "zero-based frame index (000123.pts = frame 123).")
    p.add_argument("video", help="the video the labels belong to")
    p.add_argument("--labels", required=True, metavar="DIR", help="folder of NNNNNN.pts label files")
    p.add_argument("--labels-from-other-video", action="store_true",
                   help="train on labels whose footage record names another video of the same frame size (the "
                        "same footage re-encoded); refused by default")
    p.add_argument("--scheme", default=None,
                   help="contours48, ibug68 or a scheme JSON file (default: the scheme the labels were made in "
                        "by 'keyshape label', else contours48)")
    p.add_argument("--morphs", type=int, default=120, help="morphed images added to the training set (default 120)")
    p.add_argument("-o", "--output", required=True, metavar="MODEL", help="model file to write (.npz)")
    p.set_defaults(func=_train)

    p = subparsers.add_parser("track", help="track a video with a trained model -> tracks CSV",
                              description="Track every frame of VIDEO with MODEL and write OpenFace-style tracks "
                                          "(frame,time,confidence,success,x_*,y_*,pose_*). Lost frames have "
                                          "success=0 and empty coordinates.")
    p.add_argument("video")
    p.add_argument("--model", required=True, help="model file from `keyshape train`")
    p.add_argument("-o", "--output", required=True, metavar="TRACKS.csv")
    p.add_argument("--overlay", metavar="OUT.mp4", help="also write the video with the tracked contours drawn "
                   "(tracks in one process: not with --jobs above 1)")
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="worker processes, each tracking a contiguous chunk of the video, stitched in frame "
                        "order (the same points within the tracker's convergence tolerance, checked at every "
                        "seam); default: one per core, at least 500 frames each (1 with --overlay)")
    p.add_argument("--smooth", default="none", choices=("none", "savgol", "oneeuro"),
                   help="temporal smoothing of the landmarks (default none)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=_track)


def _scheme(args) -> int:
    from keyshape.base.schemes import load_scheme

    s = load_scheme(args.name)
    print(f"{s.name}: {s.n_points} points; inter-ocular pair {s.inter_ocular}")
    for name, idx in s.contours.items():
        print(f"  contour {name:12s} {idx[0]}-{idx[-1]}{' (closed)' if s.closed[name] else ''}")
    for name, idx in s.regions.items():
        print(f"  region  {name:12s} {len(idx)} points")
    return 0


#: fewer labelled frames than this train with a warning (README: 8-20 labelled frames)
RECOMMENDED_LABELS = 8


def _check_footage(args) -> None:
    """Labels belong to the footage they were made on (their folder's ``footage.json``): another frame
    size is refused; another video (content or frame count) unless ``--labels-from-other-video``.
    A folder without a record (made before keyshape wrote one) trains, said in one line."""
    from keyshape.base.errors import InputError
    from keyshape.base.formats.labels import FOOTAGE_FILE, footage_record, read_footage

    rec = read_footage(args.labels)
    if rec is None:
        print(f"keyshape train: note: {args.labels} has no {FOOTAGE_FILE} (made before keyshape recorded the "
              f"footage of its labels): not checked against {args.video}", file=sys.stderr)
        return
    now = footage_record(args.video)
    if (now["width"], now["height"]) != (rec["width"], rec["height"]):
        raise InputError(f"these labels were made on footage of {rec['width']}x{rec['height']} ({rec.get('video')}), "
                         f"{args.video} is {now['width']}x{now['height']}: label positions are pixels of that footage",
                         args.labels)
    if (now["sha256"], now["n_frames"]) != (rec["sha256"], rec["n_frames"]) and not args.labels_from_other_video:
        raise InputError(f"these labels were made on another video ({rec.get('video')}, {rec['n_frames']} frames, "
                         f"sha256 {rec['sha256'][:12]}...; {args.video}: {now['n_frames']} frames, sha256 "
                         f"{now['sha256'][:12]}...): train on that video, or pass --labels-from-other-video if "
                         "this is the same footage re-encoded", args.labels)


def _train(args) -> int:
    import time

    from keyshape.base.errors import InputError
    from keyshape.tracker.commands import fit_model

    if args.morphs < 0:
        raise InputError(f"--morphs {args.morphs}: must be >= 0")
    _check_footage(args)
    t0 = time.perf_counter()
    model = fit_model(args.video, args.labels, args.scheme, n_morphs=args.morphs)
    seconds = time.perf_counter() - t0
    model.save(args.output)
    print(f"keyshape train: {len(model.train_poses_)} labelled frames + {model.n_samples_ - len(model.train_poses_)} "
          f"morphs, {model.k_} components ({100 * model.explained_variance_ratio_.sum():.1f}% of the variance), "
          f"{seconds:.1f} s -> {args.output}")
    n_labels = len(model.train_poses_)
    if n_labels < RECOMMENDED_LABELS:
        print(f"keyshape train: warning: only {n_labels} labelled frames; {RECOMMENDED_LABELS}-20 varied frames "
              "are recommended (the model cannot track expressions it has not seen)", file=sys.stderr)
    return 0


def _track(args) -> int:
    from keyshape.base.errors import InputError
    from keyshape.tracker.commands import track_video
    from keyshape.tracker.defaults import TrackOptions

    if args.jobs is not None and args.jobs < 1:
        raise InputError(f"--jobs {args.jobs}: must be >= 1 (or leave it out: one per core)")
    summary = track_video(args.video, args.model, args.output, overlay=args.overlay,
                          options=TrackOptions(smooth=args.smooth, jobs=args.jobs), show_progress=not args.quiet)
    print(summary.message)
    if summary.interrupted:
        return 143 if summary.terminated else 130
    if summary.truncated:
        print(f"keyshape track: warning: {args.video} ended after {summary.n_frames} of the "
              f"{summary.expected} frames its header announces (truncated or damaged file); "
              f"tracks written for the {summary.n_frames} frames decoded", file=sys.stderr)
    return 0
