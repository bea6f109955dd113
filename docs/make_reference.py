"""Write docs/reference.md from the command line itself: every command, every option, its default.

    python docs/make_reference.py            # rewrite docs/reference.md
    python docs/make_reference.py --check    # exit 1 if docs/reference.md is out of date

``tests/test_docs.py`` runs the check, so the reference cannot drift from ``keyshape --help``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REFERENCE = Path(__file__).resolve().parent / "reference.md"
REPO = REFERENCE.parents[1]

HEAD = """# Command reference

Every `keyshape` command with every option, as `keyshape COMMAND --help` gives them (this page is
generated from the parser by `docs/make_reference.py`; `tests/test_docs.py` fails when it is out of
date). Defaults are in brackets. Exit status: 0 success, 2 bad input (one line naming the file or
option), 130 Ctrl-C, 143 SIGTERM; what each command guarantees about its outputs is in
[reliability.md](reliability.md).
"""


def _subcommands(parser: argparse.ArgumentParser, prefix: str):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield from _subcommands(sub, f"{prefix} {name}") if _has_sub(sub) else [(f"{prefix} {name}", sub, helps.get(name))]


def _has_sub(parser: argparse.ArgumentParser) -> bool:
    return any(isinstance(a, argparse._SubParsersAction) for a in parser._actions)


def _default(action: argparse.Action) -> str:
    d = action.default
    if d is None or d is False or d is argparse.SUPPRESS or isinstance(action, argparse._StoreTrueAction):
        return ""
    if isinstance(d, (list, tuple)):
        d = " ".join(map(str, d))
    if "default" in (action.help or ""):
        return ""  # the help text states it
    # a path default under the checkout's parent (../shared/data/...) printed as the user sees it
    return f" [{str(d).replace(str(REPO.parent), '..')}]"


def _one(text: str | None) -> str:
    return " ".join((text or "").split()).replace("|", "\\|")


def markdown() -> str:
    from keyshape.cli import build_parser

    out = [HEAD]
    for name, sub, help_ in _subcommands(build_parser(), "keyshape"):
        usage = " ".join(sub.format_usage().split())[len("usage: "):]
        out.append(f"\n## `{name}`\n\n{_one(sub.description or help_)}\n\n`{usage}`\n\n")
        rows = []
        for a in sub._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            flag = ", ".join(f"`{s}`" for s in a.option_strings) or f"`{a.metavar or a.dest}`"
            if a.choices and not isinstance(a, argparse._SubParsersAction):
                flag += " " + "\\|".join(map(str, a.choices))
            rows.append(f"| {flag} | {_one(a.help)}{_default(a)} |")
        if rows:
            out.append("| argument | meaning [default] |\n|---|---|\n" + "\n".join(rows) + "\n")
    return "".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/reference.md is out of date")
    a = ap.parse_args(argv)
    text = markdown()
    if a.check:
        same = REFERENCE.is_file() and REFERENCE.read_text() == text
        print("docs/reference.md is " + ("up to date" if same else "out of date: run python docs/make_reference.py"))
        return 0 if same else 1
    REFERENCE.write_text(text)
    print(f"wrote {REFERENCE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
