"""The documentation matches the code: docs/reference.md is what the parser says (every command, every
option), and every command appears in README.md's command list."""
from __future__ import annotations

import runpy
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _reference():
    return runpy.run_path(str(REPO / "docs" / "make_reference.py"))


def test_reference_is_generated_from_the_parser():
    ref = _reference()
    text = (REPO / "docs" / "reference.md").read_text()
    assert text == ref["markdown"](), "docs/reference.md is out of date: run python docs/make_reference.py"


def test_reference_lists_every_option_of_every_command():
    import argparse

    from keyshape.cli import build_parser

    ref = _reference()
    text = (REPO / "docs" / "reference.md").read_text()
    commands = list(ref["_subcommands"](build_parser(), "keyshape"))
    assert len(commands) >= 15
    for name, sub, _ in commands:
        section = text.split(f"## `{name}`\n", 1)[1].split("\n## ", 1)[0]
        for action in sub._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            for flag in action.option_strings:
                assert f"`{flag}`" in section, f"{name}: {flag} missing from docs/reference.md"


def test_readme_names_every_command():
    from keyshape.cli import build_parser

    readme = (REPO / "README.md").read_text()
    for name, _, _ in _reference()["_subcommands"](build_parser(), "keyshape"):
        assert f"`{name}" in readme, f"README.md does not mention {name}"
