"""The one output rule (issue 37), proved from the command-line parser itself.

Every subcommand of ``keyshape.cli``'s parser and every string argument it takes must be declared in
``keyshape.declare.ROLES`` (input, output file, output folder, or text): a new command or option that
is not declared fails here, so no command can skip the rule. Then, for every declared output of every
command, the command is run with that output aimed at each input (by the same name, another spelling,
a symbolic link, a hard link), at a symbolic link, at a user's own file, and at a user's file that a
planted ``.keyshape-outputs.json`` claims: every run must exit 2 with one line naming the user's path,
before any work (the inputs are dummy files the command never gets to read), and change nothing.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
from pathlib import Path

import pytest

from keyshape.base.files import MANIFEST
from keyshape.cli import _subparsers, build_parser, main
from keyshape.declare import ROLES, SIDECARS

from conftest import tree as _tree


def tree(root: Path) -> dict[str, str]:
    return _tree(root, folders=True)

#: phrases of the output layer's refusals (keyshape.base.files.guard_file, keyshape.declare.check_declared)
REFUSED = ("one of the inputs", "input folder", "symbolic link", "was not written by keyshape",
           "changed since keyshape wrote it")


def _commands() -> dict[str, argparse.ArgumentParser]:
    out = {}
    for sp in _subparsers(build_parser()):
        name = sp.prog.split(" ", 1)[1]
        out[name] = sp
    return out


COMMANDS = _commands()


def _string_actions(sp: argparse.ArgumentParser):
    for a in sp._actions:
        if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)) or a.nargs == 0:
            continue
        if a.type is None or a.type is str:
            yield a


def test_every_command_and_every_string_argument_is_declared():
    assert set(COMMANDS) == set(ROLES), "declare every command in keyshape/declare.py ROLES (and only those)"
    for name, sp in COMMANDS.items():
        dests = {a.dest for a in _string_actions(sp)}
        missing = dests - set(ROLES[name])
        assert not missing, f"keyshape {name}: declare {sorted(missing)} in keyshape.declare.ROLES"
        stale = set(ROLES[name]) - {a.dest for a in sp._actions}
        assert not stale, f"keyshape {name}: ROLES names {sorted(stale)}, which the parser does not have"
    assert set(SIDECARS) <= set(ROLES)


def _argv(name: str, sp: argparse.ArgumentParser, root: Path, output_dest: str, output: str) -> tuple[list, list]:
    """argv running ``name`` with every declared input a dummy file under ``root`` and ``output_dest``
    set to ``output``; and the input paths."""
    roles = ROLES[name]
    words = name.split()
    options: list[str] = []
    positional: list[str] = []
    inputs: list[Path] = []
    for a in sp._actions:
        if isinstance(a, argparse._HelpAction) or a.nargs == 0:
            continue
        role = roles.get(a.dest)
        if a.dest == output_dest:
            value = output
        elif role == "in":
            p = root / f"in_{a.dest}.dat"
            p.write_text(f"input {a.dest}\n")
            inputs.append(p)
            value = str(p)
        elif a.required or not a.option_strings and a.nargs not in ("?", "*"):
            value = (a.choices and str(next(iter(a.choices)))) or ("1" if a.type in (int, float) else "x")
        else:
            continue
        if a.option_strings:
            options += [a.option_strings[0], value]
        else:
            positional.append(value)
    return [*words, *positional, *options], inputs


def _outputs():
    for name in sorted(ROLES):
        for dest, role in ROLES[name].items():
            if role in ("file", "folder", "file|folder"):
                yield name, dest, role


def _run(argv, capsys) -> tuple[int, str]:
    capsys.readouterr()
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    return rc, err


def _refused(argv, capsys, root: Path, shown: str) -> str | None:
    """Why the run was not a clean refusal (None when it was)."""
    before = tree(root)
    rc, err = _run(argv, capsys)
    if rc != 2 or "\n" in err or "Traceback" in err or not any(p in err for p in REFUSED) or shown not in err:
        return f"{' '.join(map(str, argv))}: rc={rc} err={err!r}"
    if tree(root) != before:
        return f"{' '.join(map(str, argv))}: changed {sorted(set(tree(root).items()) ^ set(before.items()))[:4]}"
    return None


@pytest.mark.parametrize("name, dest, role", list(_outputs()), ids=lambda v: str(v).replace(" ", "_"))
def test_every_output_is_refused_before_work(name, dest, role, tmp_path, monkeypatch, capsys):
    sp = COMMANDS[name]
    root = tmp_path / "w"
    root.mkdir()
    monkeypatch.chdir(root)
    failures = []
    is_folder = role == "folder"
    # 1. the output is an input: by its name, another spelling, a symbolic link, a hard link
    argv, inputs = _argv(name, sp, root, dest, "placeholder")
    for inp in inputs:
        spellings = [str(inp), f"./sub/../{inp.name}"]
        (root / "sub").mkdir(exist_ok=True)
        link = root / f"link_to_{inp.name}"
        link.symlink_to(inp)
        spellings.append(str(link))
        if not is_folder:
            hard = root / f"hard_{inp.name}"
            os.link(inp, hard)
            spellings.append(str(hard))
        for s in spellings:
            argv, _ = _argv(name, sp, root, dest, s)
            failures.append(_refused(argv, capsys, root, Path(s).name))
    # 2. a symbolic link (to a user's file, or folder), 3. a user's own file, 4. with a planted record
    mine = root / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("the user's")
    link = root / ("out_link" if is_folder else "out_link.json")
    link.symlink_to(mine if is_folder else mine / "notes.txt")
    argv, _ = _argv(name, sp, root, dest, str(link))
    failures.append(_refused(argv, capsys, root, link.name))
    if not is_folder:
        target = mine / "notes.txt"
        argv, _ = _argv(name, sp, root, dest, str(target))
        failures.append(_refused(argv, capsys, root, "notes.txt"))
        for record in ({"written_by": "keyshape", "outputs": {"files": ["notes.txt"], name: ["notes.txt"]}},
                       {"written_by": "keyshape", "version": 3, "outputs": {"files": ["notes.txt"]},
                        "sha256": {"notes.txt": "0" * 64}},
                       {"written_by": "keyshape", "files": ["notes.txt"]}):
            (mine / MANIFEST).write_text(json.dumps(record))
            failures.append(_refused(argv, capsys, root, "notes.txt"))
        (mine / MANIFEST).unlink()
    # 5. sidecars follow the same rule (track -o mine.csv writes mine.meta.json)
    if name in SIDECARS and dest in ("output", "out"):
        out = mine / ("x" if is_folder else "x.csv")
        args = sp.parse_args(_argv(name, sp, root, dest, str(out))[0][len(name.split()):])
        for side in SIDECARS[name](args):
            side.parent.mkdir(parents=True, exist_ok=True)
            side.write_text("the user's sidecar")
            argv, _ = _argv(name, sp, root, dest, str(out))
            failures.append(_refused(argv, capsys, root, side.name))
            side.unlink()
    failures = [f for f in failures if f]
    assert not failures, "\n".join(failures[:6])


def test_a_rerun_replaces_the_commands_own_outputs_and_records_them(tmp_path, capsys):
    """The other side of the rule: what keyshape wrote (recorded with its hash) a rerun replaces, for
    single files, sidecars and streamed outputs (track's CSV and overlay) alike; an edit stops it."""
    foot = tmp_path / "foot"
    assert main(["synth", "video", str(foot), "--frames", "16", "--size", "160x120", "--labels", "6"]) == 0
    model, tracks = tmp_path / "m.npz", tmp_path / "t.csv"
    runs = [["train", str(foot / "video.mp4"), "--labels", str(foot / "labels"),
             "-o", str(model)],
            ["track", str(foot / "video.mp4"), "--model", str(model), "-o", str(tracks), "--overlay",
             str(tmp_path / "o.mp4"), "--quiet"],
            ["select", str(tracks), "-k", "2", "--region", "mouth", "-o", str(tmp_path / "k.json")],
            ["decompose", str(tracks), "--keys", str(tmp_path / "k.json"), "-o", str(tmp_path / "w.csv")]]
    for argv in runs:
        assert main(argv) == 0, capsys.readouterr().err
        assert main(argv) == 0, capsys.readouterr().err                    # the rerun replaces its own
    record = json.loads((tmp_path / MANIFEST).read_text())
    assert set(record["outputs"]["files"]) >= {"m.npz", "t.csv", "t.meta.json", "o.mp4", "k.json", "w.csv"}
    assert record["sha256"]["t.csv"] == hashlib.sha256(tracks.read_bytes()).hexdigest()
    (tmp_path / "w.csv").write_text((tmp_path / "w.csv").read_text() + "\n")   # the user edits it
    capsys.readouterr()
    assert main(runs[-1]) == 2
    assert "changed since keyshape wrote it" in capsys.readouterr().err
    assert main([*runs[-1], "--overwrite"]) == 0
