"""The product's surface counted from the code: the command line (options per command, every default printed
once and true) and the Python functions (no public function with more than 10 parameters)."""
from __future__ import annotations

import argparse
import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = ("keyshape", "tracker", "decompose", "retarget", "data_synth")
#: the most options (``-h`` and hidden ones not counted) a command may have, and all of them together: the aim is
#: 150 in all; MOST_TOTAL holds what the commands have now and may only come down
MOST = {"solve": 10, "retarget": 12, "live": 12}
MOST_TOTAL = 150
#: public functions over 10 parameters that are still to be grouped into an options object: this list may only
#: shrink (a function here that fits, or one not here that does not, fails the test)
STILL_OVER = {"retarget/output/preview_cli.py:write_preview",
              "keyshape/base/formats/gltf.py:write_glb", "keyshape/base/formats/usd.py:write_usd",
              "tracker/eigenpoints.py:fit_region", "tracker/commands.py:iter_track",
              "tracker/chunked.py:iter_track_chunked"}


def commands() -> dict[str, argparse.ArgumentParser]:
    """Every leaf command's parser, by its name (``synth video`` for a group's)."""
    from keyshape.cli import build_parser

    out = {}

    def walk(parser, prefix):
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        for a in subs:
            for name, sp in a.choices.items():
                walk(sp, f"{prefix} {name}".strip())
        if not subs and prefix:
            out[prefix] = parser

    walk(build_parser(), "")
    return out


#: options every command has, added once for all in keyshape/cli.py (counted like ``-h``, not per command)
COMMON = {"--overwrite"}


def options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The options a user sees: not ``-h`` or the options every command shares (:data:`COMMON`), not the hidden
    ones, not the positional arguments."""
    return [a for a in parser._actions if a.option_strings and not isinstance(a, argparse._HelpAction)
            and a.help != argparse.SUPPRESS and not COMMON & set(a.option_strings)]


def test_command_line_options_counted():
    counts = {name: len(options(p)) for name, p in commands().items()}
    over = {name: (counts[name], most) for name, most in MOST.items() if counts[name] > most}
    assert not over, f"commands with more options than their aim (count, aim): {over}"
    assert sum(counts.values()) <= MOST_TOTAL, f"{sum(counts.values())} options in all: {counts}"


def test_every_default_printed_once_and_true():
    for name, p in commands().items():
        text = p.format_help()
        for a in options(p):
            h = (a.help or "") % {"default": a.default, "prog": "x", "dest": a.dest} if a.help else ""
            shown = p._get_formatter()._expand_help(a) if a.help else ""
            assert shown.count("(default") <= 1, f"{name} {a.option_strings[0]}: two defaults in {shown!r}"
            if isinstance(a, argparse._StoreFalseAction):
                assert "(default: True)" not in shown, f"{name} {a.option_strings[0]} prints (default: True): {h!r}"
        assert not re.search(r"\(default[^)]*\)[^\n]*\(default", text), name


def public_functions_over(limit: int = 10) -> set[str]:
    over = set()
    for root in PACKAGE:
        for f in sorted((REPO / root).rglob("*.py")):
            for node in ast.walk(ast.parse(f.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
                    a = node.args
                    names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
                    n = len(names) + (a.vararg is not None) + (a.kwarg is not None)
                    n -= bool(names) and names[0] in ("self", "cls")
                    if n > limit:
                        over.add(f"{f.relative_to(REPO).as_posix()}:{node.name}")
    return over


def test_no_public_function_takes_more_than_10_parameters():
    over = public_functions_over()
    assert not over - STILL_OVER, f"public functions with more than 10 parameters: {sorted(over - STILL_OVER)}"
    assert not STILL_OVER - over, f"grouped already, take them off STILL_OVER: {sorted(STILL_OVER - over)}"


@pytest.mark.parametrize("flag", ["--keep-yaw-slide", "--keep-yaw-stretch", "--pitch-parallax", "--gaze-lids",
                                  "--keep-rest", "--sparsity", "--head-pose"])
def test_solve_experiments_are_off_the_command_line(flag):
    assert flag not in {s for a in options(commands()["solve"]) for s in a.option_strings}
