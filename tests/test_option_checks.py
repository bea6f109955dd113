"""Every option and degenerate input refused before the work, one line naming it (issue 37, item 4).

The same option means the same in every command (``--fps`` in ``solve`` as in ``retarget`` and ``synth``):
the checks are argparse types in :mod:`keyshape.base.options`. Each case here is refused while the
arguments are parsed or the first input is read, so the inputs may be dummies.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from keyshape.base.errors import InputError
from keyshape.cli import main


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err and "\n" not in err and "Traceback" not in err, err
    return err


SOLVE = ["solve", "t.csv", "--keys", "k.json", "--rig", "rig", "-o", "c.csv"]


@pytest.mark.parametrize("argv, phrase", [
    (["synth", "video", "v", "--frames", "1e11"], "--frames 1e11"),
    (["synth", "video", "v", "--frames", "100000000000"], "--frames 100000000000"),
    (["synth", "face3d", "v", "--fps", "1e9"], "--fps 1e9"),
    (["synth", "video", "v", "--fps", "nan"], "--fps nan"),
    (["demo", "d", "--frames", "0"], "--frames 0"),
    ([*SOLVE, "--livelink", "--fps", "1e-300"], "--fps 1e-300"),
    ([*SOLVE, "--fps", "nan"], "--fps nan"),
    ([*SOLVE, "--fps", "0"], "--fps 0"),
    ([*SOLVE, "--fps", "-30"], "--fps -30"),
    ([*SOLVE, "--head-units", "nan"], "--head-units nan"),
    (["retarget", "w.csv", "--targets", "t", "--fps", "0", "-o", "o.glb"], "--fps 0"),
    (["retarget", "w.csv", "--targets", "t", "--fps", "inf", "-o", "o.glb"], "--fps inf"),
    (["retarget", "w.csv", "--targets", "t", "--head-units", "-1", "-o", "o.glb"], "--head-units -1"),
    (["live", "99999999999999999999", "--model", "m.npz", "--keys", "k.json", "--poses", "p.json", "--rig", "r"],
     "camera 99999999999999999999"),
    (["live", "v.mp4", "--model", "m.npz", "--keys", "k.json", "--poses", "p.json", "--rig", "r",
      "--local-port", "99999999999999999999"], "--local-port"),
    (["label", "v.mp4", "-o", "lab", "--port", "70000"], "--port 70000"),
    (["synth", "video", "v", "--frames", "100000", "--preview", "sheet.txt"], "--preview"),
    (["pose-edit", "missing.json", "--rig", "rig", "--port", "0"], "missing.json"),
])
def test_a_bad_option_is_one_line_before_work(tmp_path, monkeypatch, capsys, argv, phrase):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert phrase in one_line(capsys)
    assert list(tmp_path.iterdir()) == []


def test_one_frame_rate_rule_everywhere():
    """Every --fps option of every command is the one shared check."""
    import argparse

    from keyshape.base import options
    from keyshape.cli import _subparsers, build_parser
    for sp in _subparsers(build_parser()):
        for a in sp._actions:
            if "--fps" in a.option_strings:
                assert a.type is options.fps, sp.prog
            if "--head-units" in a.option_strings:
                assert a.type is options.head_units, sp.prog
            if {"--port", "--local-port"} & set(a.option_strings):
                assert a.type is options.port, sp.prog
    with pytest.raises(argparse.ArgumentTypeError):
        options.fps("1e-300")


def _tracks(path, points, time=None, model=None):
    from keyshape.base.formats.tracks import Tracks, write_tracks
    n = len(points)
    write_tracks(path, Tracks(np.arange(n), np.arange(n) / 30.0 if time is None else time, np.ones(n),
                              np.ones(n, bool), points, np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (n, 1, 1)),
                              {"model": model} if model else {}))


def test_degenerate_tracks_are_refused_naming_the_file(tmp_path):
    from keyshape.base.formats.tracks import read_tracks
    rng = np.random.default_rng(0)
    pts = rng.normal(100, 10, (5, 48, 2))
    collapsed = pts.copy()
    collapsed[2] = 50.0                                         # one tracked frame with every point on one spot
    _tracks(tmp_path / "c.csv", collapsed)
    with pytest.raises(InputError, match=r"c\.csv.*one spot"):
        read_tracks(tmp_path / "c.csv")
    _tracks(tmp_path / "ok.csv", pts)
    text = (tmp_path / "ok.csv").read_text().splitlines()
    rows = [line.split(",") for line in text[1:]]
    for i, r in enumerate(rows):                               # times that step by 1e-9 s
        r[1] = f"{i * 1e-9:.12g}"
    (tmp_path / "fast.csv").write_text("\n".join([text[0], *(",".join(r) for r in rows)]) + "\n")
    with pytest.raises(InputError, match=r"fast\.csv.*do not advance"):
        read_tracks(tmp_path / "fast.csv")


@pytest.mark.parametrize("points, phrase", [
    ([7] * 48, "degenerate landmark map"),
    ([[[1, float("nan")], [2, 0.5]]] + list(range(47)), "not a finite number"),
])
def test_degenerate_rig_landmarks_are_refused(tmp_path, points, phrase):
    from keyshape.base.formats.poses import read_rig_landmarks
    path = tmp_path / "lm.json"
    path.write_text(json.dumps({"format": "keyshape-rig-landmarks", "version": 1, "scheme": "contours48",
                                "n_vertices": 60, "points": points}))
    with pytest.raises(InputError, match=phrase):
        read_rig_landmarks(path)


def test_solve_refuses_keys_of_another_tracker_model(tmp_path, capsys):
    """As decompose does: keys chosen from another model's tracks are refused before the rig is read."""
    rng = np.random.default_rng(1)
    _tracks(tmp_path / "t.csv", rng.normal(100, 10, (4, 48, 2)), model="sha256:" + "a" * 64)
    from test_rig_poses import TRUE, actor_keys

    from keyshape.base.formats.keys import write_keys
    write_keys(tmp_path / "k.json", "contours48", 48, actor_keys(TRUE), source={"model": "sha256:" + "b" * 64})
    rc = main(["solve", str(tmp_path / "t.csv"), "--keys", str(tmp_path / "k.json"), "--rig", str(tmp_path / "rig"),
               "-o", str(tmp_path / "c.csv")])
    err = one_line(capsys)
    assert rc == 2 and "another tracker model" in err and "k.json" in err, err
    assert not (tmp_path / "c.csv").exists()
