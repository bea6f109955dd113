"""Command-line registration for the tracker stage: ``keyshape scheme`` (and ``train``/``track``)."""
from __future__ import annotations


def register(subparsers) -> None:
    """Add the tracker's subcommands to ``subparsers``."""
    p = subparsers.add_parser("scheme", help="print a landmark scheme (points, contours, regions)")
    p.add_argument("name", nargs="?", default="contours48", help="contours48, ibug68 or a scheme JSON file")
    p.set_defaults(func=_scheme)


def _scheme(args) -> int:
    from tracker.schemes import load_scheme

    s = load_scheme(args.name)
    print(f"{s.name}: {s.n_points} points; inter-ocular pair {s.inter_ocular}")
    for name, idx in s.contours.items():
        print(f"  contour {name:12s} {idx[0]}-{idx[-1]}{' (closed)' if s.closed[name] else ''}")
    for name, idx in s.regions.items():
        print(f"  region  {name:12s} {len(idx)} points")
    return 0
