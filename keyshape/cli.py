"""The ``keyshape`` command: one entry, subcommands registered by the stage that runs them.

Each stage keeps its own command code (``tracker/cli.py``, ``decompose/cli.py``,
...) exposing ``register(subparsers)``; this module only collects them, runs the
chosen one and turns :class:`~pipeline.errors.KeyshapeError` into a one-line
message and exit status 2 (no traceback), and Ctrl-C into status 130.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

from keyshape.base.errors import KeyshapeError

# (module, group): group None registers top-level subcommands; "synth" registers
# under ``keyshape synth ...``. Order is the order of ``keyshape --help``.
COMMAND_MODULES: list[tuple[str, str | None]] = [
    ("keyshape.demo", None),
    ("keyshape.data_synth.video_cli", "synth"),
    ("keyshape.data_synth.mocap_cli", "synth"),
    ("keyshape.tracker.labelling.cli", None),
    ("keyshape.tracker.cli", None),
    ("keyshape.decompose.cli", None),
    ("keyshape.retarget.cli", None),
    ("keyshape.retarget.mocap.cli", None),
    ("keyshape.retarget.dense_cli", None),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="keyshape",
        description="Turn a filmed facial performance (video or 3D markers) into animation "
                    "of an artist's own blendshapes.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    groups: dict[str, argparse._SubParsersAction] = {}
    for module_name, group in COMMAND_MODULES:
        module = importlib.import_module(module_name)
        if group is None:
            module.register(sub)
        else:
            if group not in groups:
                gp = sub.add_parser(group, help="make synthetic data with exact ground truth")
                groups[group] = gp.add_subparsers(dest=f"{group}_command", metavar="KIND")
                gp.set_defaults(func=lambda args, _gp=gp: _gp.error("choose what to synthesise"))
            module.register(groups[group])
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``keyshape`` with ``argv`` (default ``sys.argv[1:]``); return the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        rc = args.func(args)
    except KeyshapeError as exc:
        print(f"keyshape {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nkeyshape {args.command}: interrupted; finished outputs are kept, partial ones removed",
              file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
