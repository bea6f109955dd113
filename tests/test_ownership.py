"""Ownership of folder outputs (issue 27): a command replaces and prunes only what the same kind of
command wrote into that folder before; never an input, never anything outside the folder, never
through a link; the ownership record (``.keyshape-outputs.json``) is untrusted input.

Each command-line case walks the whole folder tree before and after (the SHA-256 of every file)
and asserts that nothing but the command's own earlier outputs changed or went away.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from keyshape.base.errors import InputError
from keyshape.base.files import MANIFEST, atomic_dir, check_output_dir
from keyshape.cli import main

from conftest import tree


def assert_kept(before: dict, after: dict, may_change: set[str] = frozenset()) -> None:
    """Every file of ``before`` is in ``after`` with the same content, except ``may_change``."""
    lost = sorted(k for k in before if k not in after and k not in may_change)
    changed = sorted(k for k in before if k in after and after[k] != before[k] and k not in may_change)
    assert not lost, f"deleted: {lost[:5]}"
    assert not changed, f"replaced: {changed[:5]}"


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err and "\n" not in err and "Traceback" not in err, err
    return err


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("own") / "d2"
    with pytest.MonkeyPatch.context() as mp:                            # a small demo: 4 labels, 2 keys
        mp.setattr("keyshape.demo.LABELS", 4)
        mp.setattr("keyshape.demo.KEYS", 2)
        assert main(["demo", str(d), "--frames", "10"]) == 0
    from keyshape.base.formats.keys import read_keys_source                # the demo's key set names its model
    assert read_keys_source(d / "keys.json")["model"].startswith("sha256:")
    return d


@pytest.fixture
def d2(demo_dir, tmp_path) -> Path:
    d = tmp_path / "d2"
    shutil.copytree(demo_dir, d, symlinks=True)
    return d


def _outputs(folder: Path) -> dict:
    return json.loads((folder / MANIFEST).read_text())["outputs"]


# --------------------------------------------------------------------------- the reported data loss
def test_retarget_into_the_demo_folder_keeps_the_demo(d2):
    before = tree(d2)
    assert main(["retarget", str(d2 / "weights.csv"), "--targets", str(d2 / "targets"), "-o", str(d2)]) == 0
    after = tree(d2)
    assert_kept(before, after, {MANIFEST})
    new = set(after) - set(before)
    assert new and all(n.startswith("frame_") and n.endswith(".obj") for n in new)
    outs = _outputs(d2)
    assert sorted(outs["retarget"]) == sorted(new) and "demo" in outs
    # a second retarget prunes only its own frames; the demo is still whole
    before = tree(d2)
    assert main(["retarget", str(d2 / "weights.csv"), "--targets", str(d2 / "targets"), "-o", str(d2)]) == 0
    assert_kept(before, tree(d2), {MANIFEST})
    assert tree(d2).keys() == before.keys()


def test_demo_rerun_keeps_other_commands_files(d2, monkeypatch):
    monkeypatch.setattr("keyshape.demo.LABELS", 4)
    monkeypatch.setattr("keyshape.demo.KEYS", 2)
    assert main(["retarget", str(d2 / "weights.csv"), "--targets", str(d2 / "targets"), "-o", str(d2)]) == 0
    frames = {k: v for k, v in tree(d2).items() if k.startswith("frame_")}
    (d2 / "notes.txt").write_text("mine")
    assert main(["demo", str(d2), "--frames", "10"]) == 0
    after = tree(d2)
    assert all(after.get(k) == v for k, v in frames.items())
    assert (d2 / "notes.txt").read_text() == "mine"


def test_compare_then_retarget_into_one_folder(d2, tmp_path):
    out = tmp_path / "out"
    assert main(["compare", str(d2 / "tracks.csv"), "-o", str(out), "--kmax", "2", "--methods", "spread", "--region", "mouth"]) == 0
    before = tree(out)
    assert main(["retarget", str(d2 / "weights.csv"), "--targets", str(d2 / "targets"), "-o", str(out)]) == 0
    after = tree(out)
    assert_kept(before, after, {MANIFEST})
    assert (out / "errors.csv").is_file() and (out / "errors.png").is_file()
    assert set(_outputs(out)) == {"compare", "retarget"}


def test_compare_dot_inside_the_demo_folder(d2, monkeypatch):
    monkeypatch.chdir(d2)
    before = tree(d2)
    assert main(["compare", "tracks.csv", "-o", ".", "--kmax", "2", "--methods", "spread", "--region", "mouth"]) == 0
    after = tree(d2)
    assert_kept(before, after, {MANIFEST})
    assert set(after) - set(before) == {"errors.csv", "errors.png"}


def test_a_command_does_not_replace_another_commands_file(d2, capsys):
    (d2 / "frame_000000.obj").write_text("the demo's? no: a user's file with keyshape's name")
    before = tree(d2)
    assert main(["retarget", str(d2 / "weights.csv"), "--targets", str(d2 / "targets"), "-o", str(d2)]) == 2
    assert "frame_000000.obj" in one_line_error(capsys)
    assert tree(d2) == before


# --------------------------------------------------------------------------- the record is untrusted
@pytest.mark.parametrize("entry", ["ABS", "../victim.txt", "a/../../victim.txt", "./x", "a//b", "", 3, None,
                                   "C:\\victim.txt", "sub\\..\\x", MANIFEST])
@pytest.mark.parametrize("legacy", [False, True])
def test_a_bad_record_is_an_error_not_a_deletion_list(d2, tmp_path, capsys, entry, legacy):
    victim = tmp_path / "victim.txt"
    victim.write_text("the user's")
    if entry == "ABS":
        entry = str(victim)
    record = {"written_by": "keyshape", "files": [entry]} if legacy else \
        {"written_by": "keyshape", "outputs": {"retarget": [entry], "demo": []}}
    (d2 / MANIFEST).write_text(json.dumps(record))
    before, outside = tree(d2), tree(tmp_path)
    assert main(["retarget", str(d2 / "weights.csv"), "--targets", str(d2 / "targets"), "-o", str(d2)]) == 2
    assert MANIFEST in one_line_error(capsys)
    assert tree(d2) == before and tree(tmp_path) == outside and victim.read_text() == "the user's"


@pytest.mark.parametrize("text", ["not json", "[]", '{"files": []}', '{"written_by": "other", "files": []}',
                                  '{"written_by": "keyshape", "outputs": []}',
                                  '{"written_by": "keyshape", "outputs": {"retarget": "x"}}',
                                  '{"written_by": "keyshape", "outputs": {"": ["x"]}}',
                                  '{"written_by": "keyshape"}', "[" * 100000])
def test_malformed_records_are_refused_before_work(tmp_path, text):
    out = tmp_path / "o"
    out.mkdir()
    (out / MANIFEST).write_text(text)
    (out / "x").write_text("keep")
    with pytest.raises(InputError, match="ownership record"):
        check_output_dir(out)
    with pytest.raises(InputError, match="ownership record"):
        with atomic_dir(out, kind="retarget") as d:
            (d / "y").write_text("new")
    assert (out / "x").read_text() == "keep" and not (out / "y").exists()


def test_a_record_that_is_a_link_is_refused(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (tmp_path / "elsewhere.json").write_text(json.dumps({"written_by": "keyshape", "files": []}))
    (out / MANIFEST).symlink_to(tmp_path / "elsewhere.json")
    with pytest.raises(InputError, match="not a plain file"):
        check_output_dir(out)


def test_recorded_links_are_never_followed(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "victim.txt").write_text("the user's")
    (outside / "f").write_text("the user's too")
    out = tmp_path / "o"
    out.mkdir()
    (out / "link").symlink_to(outside, target_is_directory=True)
    (out / "sym.txt").symlink_to(outside / "victim.txt")
    (out / MANIFEST).write_text(json.dumps({"written_by": "keyshape",
                                            "outputs": {"retarget": ["link/victim.txt", "sym.txt"]}}))
    before = tree(tmp_path)
    with atomic_dir(out, kind="retarget") as d:                  # prunes: neither the link nor through it
        (d / "new.txt").write_text("n")
    assert_kept(before, tree(tmp_path), {f"o/{MANIFEST}"})
    assert (outside / "victim.txt").read_text() == "the user's" and (out / "sym.txt").is_symlink()
    with pytest.raises(InputError, match="symbolic link"):      # never writes through a linked folder
        with atomic_dir(out, kind="retarget", overwrite=True) as d:
            (d / "link").mkdir()
            (d / "link" / "f").write_text("x")
    assert (outside / "f").read_text() == "the user's too"


# --------------------------------------------------------------------------- kinds, inputs, legacy records
def test_each_kind_prunes_only_its_own(tmp_path):
    out = tmp_path / "o"
    with atomic_dir(out, kind="compare") as d:
        (d / "errors.csv").write_text("c")
    with atomic_dir(out, kind="retarget") as d:
        (d / "a.obj").write_text("1")
        (d / "sub").mkdir()
        (d / "sub" / "b.obj").write_text("1")
    with atomic_dir(out, kind="retarget") as d:
        (d / "c.obj").write_text("2")
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == [MANIFEST, "c.obj", "errors.csv"]
    with pytest.raises(InputError, match="written by keyshape compare"):
        with atomic_dir(out, kind="retarget") as d:
            (d / "errors.csv").write_text("r")
    assert (out / "errors.csv").read_text() == "c"
    with atomic_dir(out, kind="retarget", overwrite=True) as d:     # --overwrite: taken over, not pruned later
        (d / "errors.csv").write_text("r")
    assert json.loads((out / MANIFEST).read_text())["outputs"] == {"retarget": ["errors.csv"]}


def test_inputs_are_never_replaced_or_pruned(tmp_path):
    out = tmp_path / "o"
    with atomic_dir(out, kind="retarget") as d:
        (d / "targets").mkdir()
        (d / "targets" / "a.obj").write_text("old output, now an input")
        (d / "w.csv").write_text("w")
    before = tree(out)
    with atomic_dir(out, kind="retarget", inputs=[out / "targets", out / "w.csv"]) as d:
        (d / "frame.obj").write_text("f")                       # not written: targets/a.obj, w.csv -> kept
    assert_kept(before, tree(out), {MANIFEST})
    assert json.loads((out / MANIFEST).read_text())["outputs"] == {"retarget": ["frame.obj"]}
    for rel in ("targets/a.obj", "targets/new.obj"):            # a file inside an input folder: refused
        with pytest.raises(InputError, match="would overwrite its input"):
            with atomic_dir(out, kind="retarget", inputs=[out / "targets"], overwrite=True) as d:
                (d / rel).parent.mkdir(parents=True, exist_ok=True)
                (d / rel).write_text("x")
    assert not (out / "targets" / "new.obj").exists()
    os.link(out / "w.csv", out / "hard.csv")                     # a hard link of an input is the input
    with pytest.raises(InputError, match="would overwrite its input"):
        with atomic_dir(out, kind="retarget", inputs=[out / "w.csv"], overwrite=True) as d:
            (d / "hard.csv").write_text("x")
    assert (out / "w.csv").read_text() == "w"


def test_an_output_folder_inside_an_input_folder_touches_no_input(d2):
    out = d2 / "targets" / "frames"
    before = tree(d2)
    args = ["retarget", str(d2 / "weights.csv"), "--targets", str(d2 / "targets"), "-o", str(out)]
    assert main(args) == 0 and main(args) == 0                  # and a rerun replaces its own frames
    after = tree(d2)
    assert_kept(before, after)
    assert all(k.startswith("targets/frames/") for k in set(after) - set(before))


def test_an_input_folder_inside_the_output_gets_no_new_file(tmp_path):
    out = tmp_path / "o"
    (out / "targets").mkdir(parents=True)
    (out / "targets" / "a.obj").write_text("target")
    with pytest.raises(InputError, match="would overwrite its input"):
        with atomic_dir(out, kind="retarget", inputs=[out / "targets"], overwrite=True) as d:
            (d / "targets").mkdir()
            (d / "targets" / "frame_000000.obj").write_text("x")     # would be read as a target next time
    assert sorted(p.name for p in (out / "targets").iterdir()) == ["a.obj"]


def test_legacy_records_are_claims_without_proof_never_replaced_or_pruned(tmp_path):
    """A record without content hashes (an older keyshape's, or a planted one) proves nothing: its
    files are replaced only with --overwrite and never pruned."""
    out = tmp_path / "o"
    out.mkdir()
    (out / "a").write_text("old a")
    (out / "b").write_text("old b")
    (out / MANIFEST).write_text(json.dumps({"written_by": "keyshape", "files": ["a", "b"]}))
    with pytest.raises(InputError, match="exists and was written by keyshape legacy"):
        with atomic_dir(out, kind="demo") as d:
            (d / "a").write_text("new a")
    assert (out / "a").read_text() == "old a"
    with atomic_dir(out, kind="demo", overwrite=True) as d:
        (d / "a").write_text("new a")
    assert (out / "a").read_text() == "new a" and (out / "b").read_text() == "old b"
    assert json.loads((out / MANIFEST).read_text())["outputs"] == {"demo": ["a"], "legacy": ["b"]}
    with atomic_dir(out, kind="demo") as d:
        (d / "c").write_text("c")
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "b", "c"]


@pytest.mark.parametrize("claims", [["precious.txt", "sub/notes.md"]])
def test_a_planted_record_is_verified_against_content_hashes(tmp_path, claims):
    """issue 37: a record listing a user's files under the run's own kind deletes nothing and replaces nothing."""
    out = tmp_path / "d"
    (out / "sub").mkdir(parents=True)
    (out / "precious.txt").write_text("mine")
    (out / "sub" / "notes.md").write_text("mine too")
    for sha in ({}, {c: "0" * 64 for c in claims}):
        (out / MANIFEST).write_text(json.dumps({"written_by": "keyshape", "outputs": {"synth video": claims},
                                                "sha256": sha}))
        with atomic_dir(out, kind="synth video") as d:
            (d / "video.mp4").write_text("v")
        assert (out / "precious.txt").read_text() == "mine" and (out / "sub" / "notes.md").read_text() == "mine too"
        with pytest.raises(InputError, match="precious.txt"):
            with atomic_dir(out, kind="synth video") as d:
                (d / "precious.txt").write_text("v")
        assert (out / "precious.txt").read_text() == "mine"
        (out / "video.mp4").unlink()


# --------------------------------------------------------------------------- write order: data before sidecar
def _tracks(value: float, model: str):
    import numpy as np

    from keyshape.base.formats.tracks import Tracks
    n = 3
    return Tracks(np.arange(n), np.arange(n) / 30.0, np.ones(n), np.ones(n, bool),
                  np.full((n, 4, 2), value) + np.arange(4)[None, :, None],          # 4 points, not collapsed
                  np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (n, 1, 1)), {"model": model})


@pytest.mark.parametrize("fail", ["csv", "sidecar"])
def test_a_failed_tracks_write_keeps_the_old_csv_and_its_sidecar(tmp_path, monkeypatch, fail):
    import errno

    import keyshape.base.formats.tracks as tr
    path = tmp_path / "t.csv"
    tr.write_tracks(path, _tracks(5.0, "sha256:old"))
    before = tree(tmp_path)

    real_fsync = os.fsync

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    def csv_full(fd):                                           # the disk fills while the CSV is written
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".csv"):
            full()
        real_fsync(fd)
    if fail == "csv":
        monkeypatch.setattr(os, "fsync", csv_full)
    else:
        monkeypatch.setattr(tr, "write_json", full)
    with pytest.raises(OSError):
        tr.write_tracks(path, _tracks(7.0, "sha256:new"))
    monkeypatch.undo()
    assert tree(tmp_path) == before
    t = tr.read_tracks(path)
    assert t.meta.get("model") == "sha256:old" and float(t.points[0, 0, 0]) == 5.0
