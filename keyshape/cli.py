"""The ``keyshape`` command: one entry, subcommands registered by the stage that runs them.

Each stage keeps its own command code (``tracker/cli.py``, ``decompose/cli.py``,
...) exposing ``register(subparsers)``; this module only collects them, runs the
chosen one and turns :class:`~keyshape.base.errors.KeyshapeError` and every ``OSError``
(unreadable or unwritable file, disk full) into a one-line message and exit status 2 (no
traceback), Ctrl-C into status 130 and SIGTERM into 143 (cleanup runs for both).
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import re
import signal
import sys
from typing import Sequence

from keyshape.base.errors import InputError, KeyshapeError

# (module, group): group None registers top-level subcommands; "synth" registers
# under ``keyshape synth ...``. Order is the order of ``keyshape --help``.
COMMAND_MODULES: list[tuple[str, str | None]] = [
    ("keyshape.demo", None),
    ("keyshape.animate", None),
    ("keyshape.data_synth.video_cli", "synth"),
    ("keyshape.data_synth.mocap_cli", "synth"),
    ("keyshape.data_synth.face3d_cli", "synth"),
    ("keyshape.tracker.labelling.cli", None),
    ("keyshape.tracker.cli", None),
    ("keyshape.decompose.cli", None),
    ("keyshape.retarget.rig.pose_cli", None),
    ("keyshape.retarget.rig.solve_cli", None),
    ("keyshape.retarget.cli", None),
    ("keyshape.retarget.output.preview_cli", None),
    ("keyshape.retarget.rig.landmarks_cli", None),
    ("keyshape.live", None),
    ("keyshape.retarget.mocap.cli", None),
    ("keyshape.retarget.dense.cli", None),
    ("keyshape.batch", None),
]


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (``keyshape COMMAND: error: argument --fps: ...``, exit 2);
    ``keyshape COMMAND --help`` shows the usage."""

    def error(self, message: str):
        m = re.fullmatch(r"argument ([^:]+): (.*)", message, re.S)
        if m:                       # "argument --port: 99999: a port must be ..." -> "--port 99999: a port ..."
            opt, rest = m.group(1).split("/")[0], m.group(2)
            own = not rest.startswith(("invalid ", "expected ", "ambiguous ", "one of ", "not allowed "))
            message = f"{opt} {rest}" if own else f"{opt}: {rest}"
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
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
    for sp in _subparsers(parser):
        if issubclass(sp.formatter_class, argparse.ArgumentDefaultsHelpFormatter):
            sp.formatter_class = DefaultsOnce   # each default printed once and true
        if not any("--overwrite" in a.option_strings for a in sp._actions):
            sp.add_argument("--overwrite", action="store_true",
                            help="replace an existing output file that keyshape's record does not show it wrote "
                                 "(never an input, never a symbolic link)")
    return parser


class DefaultsOnce(argparse.ArgumentDefaultsHelpFormatter):
    """Each option's default printed once and true: not where its help says it already (``(default...``), not
    for a switch (``store_true``/``store_false``: its help says what it does) and not for None (the help says
    what happens without it)."""

    def _get_help_string(self, action):
        h = action.help or ""
        if ("(default" in h or action.default is None or isinstance(action.default, bool)
                or isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction,
                                       argparse.BooleanOptionalAction))):
            return h
        return super()._get_help_string(action)


def _subparsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """Every leaf subcommand's parser (``synth video``, ``track``, ...)."""
    out = []
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for sp in a.choices.values():
                subs = _subparsers(sp)
                out += subs if subs else [sp]
    return out


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every ``finally``/cleanup runs (exit status 143)."""


def _raise_terminated(signum, frame):
    raise Terminated()


@contextlib.contextmanager
def sigterm_as_interrupt():
    """While active (main thread only), SIGTERM raises :class:`Terminated`, a KeyboardInterrupt."""
    try:
        old = signal.signal(signal.SIGTERM, _raise_terminated)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _command_name(args) -> str:
    sub = getattr(args, "synth_command", None) if args.command == "synth" else None
    return f"{args.command} {sub}" if sub else str(args.command)


#: the largest seed numpy's generators accept
SEED_MAX = 2 ** 32 - 1


def _check_common_options(args) -> None:
    """Options several commands share, checked before any work: ``--seed`` (numpy accepts
    0..2**32-1) and ``--port`` (0: any free port, else up to 65535)."""
    seed = getattr(args, "seed", None)
    if isinstance(seed, int) and not 0 <= seed <= SEED_MAX:
        raise InputError(f"--seed {seed}: must be an integer from 0 to {SEED_MAX}")
    port = getattr(args, "port", None)
    if isinstance(port, int) and not 0 <= port <= 65535:
        raise InputError(f"--port {port}: must be from 0 (any free port) to 65535")


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``keyshape`` with ``argv`` (default ``sys.argv[1:]``); return the exit status.

    Exit statuses: 0 success, 1 usage without a command, 2 bad input or a file
    that cannot be read or written (one line on standard error, no traceback),
    130 interrupted by Ctrl-C, 143 terminated by SIGTERM. An interruption
    keeps every earlier complete output and removes temporary files.
    """
    from keyshape.base.files import describe_os_error

    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:            # a bad option (one line, exit 2) or --help (0)
        return exc.code if isinstance(exc.code, int) else 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    name = _command_name(args)
    try:
        _check_common_options(args)
        from keyshape.base.files import run_rules
        from keyshape.declare import check_declared
        run = check_declared(name, args)
        with sigterm_as_interrupt(), (run_rules(run) if run is not None else contextlib.nullcontext()):
            rc = args.func(args)
    except KeyshapeError as exc:
        print(f"keyshape {name}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"keyshape {name}: error: {describe_os_error(exc)}", file=sys.stderr)
        return 2
    except UnicodeDecodeError as exc:
        print(f"keyshape {name}: error: an input file is not UTF-8 text ({exc.reason} at byte {exc.start})",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        term = isinstance(exc, Terminated)
        print(f"\nkeyshape {name}: {'terminated' if term else 'interrupted'}; earlier outputs are untouched, "
              "temporary files removed", file=sys.stderr)
        return 143 if term else 130
    return int(rc or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
