"""The Python API (keyshape.api): the README's ten-line example runs as written, the API gives
what the commands give, and ``keyshape.<name>`` loads the API lazily."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from synth_library import grid_targets

REPO = Path(__file__).resolve().parents[1]
REGIONS = {"mouth": 8, "eyes": 8}


def readme_example() -> str:
    text = (REPO / "README.md").read_text()
    section = text[text.index("### Video path in Python"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


@pytest.fixture(scope="module")
def footage(tmp_path_factory):
    from keyshape.data_synth.video import synthesize

    d = tmp_path_factory.mktemp("api")
    out = synthesize(d / "synth", frames=40, seed=3, labels=12)
    shutil.copy(out["video"], d / "take1.mp4")
    shutil.copytree(out["labels"], d / "take1_labels")
    (d / "targets").mkdir()
    (d / "regions.json").write_text(json.dumps(grid_targets(d / "targets", REGIONS)))
    return d


def test_readme_example_runs_as_written(footage, monkeypatch, capsys):
    code = readme_example()
    assert len([ln for ln in code.splitlines() if ln.strip()]) <= 10, code
    monkeypatch.chdir(footage)
    exec(compile(code, "README.md", "exec"), {})
    printed = capsys.readouterr().out.strip()
    assert printed == f"(40, 16) (40, {6 * 6}, 3)"
    gltf = pygltflib.GLTF2().load(str(footage / "take1.glb"))
    assert len(gltf.meshes[0].primitives[0].targets) == 16
    assert gltf.accessors[gltf.animations[0].samplers[0].input].count == 40
    for name in ("keys.json", "weights.csv", "take1_model.npz"):
        assert (footage / name).stat().st_size > 0


def test_api_matches_the_commands(footage, tmp_path):
    """``keyshape track/select/decompose`` on files give what the API gives in memory (to the files'
    printed precision: tracks %.4f, weights %.6f)."""
    from keyshape import api
    from keyshape.cli import main

    assert (footage / "take1_model.npz").is_file() or pytest.skip("needs the README example's model")
    model = api.AppearanceModel.load(footage / "take1_model.npz")
    tracks = api.track(footage / "take1.mp4", model)
    assert main(["track", str(footage / "take1.mp4"), "--model", str(footage / "take1_model.npz"),
                 "-o", str(tmp_path / "t.csv"), "--quiet"]) == 0
    from_file = api.read_tracks(tmp_path / "t.csv")
    np.testing.assert_array_equal(from_file.frame, tracks.frame)
    np.testing.assert_array_equal(from_file.success, tracks.success)
    np.testing.assert_allclose(from_file.points, tracks.points, atol=5e-5)

    # the same defaults: no option on either side (the API's select once disagreed with the command's
    # on the selector, the weights' origin and near-duplicate keys)
    keys = api.select(from_file, 4, regions=["mouth"])
    assert main(["select", str(tmp_path / "t.csv"), "-k", "4", "--region", "mouth",
                 "-o", str(tmp_path / "k.json")]) == 0
    from_cmd = api.Keys.load(tmp_path / "k.json")
    assert from_cmd.head_pose == keys.head_pose
    for a, b in zip(from_cmd.regions, keys.regions):
        assert (a.method, a.rest_frame) == (b.method, b.rest_frame) == ("greedy", b.rest_frame)
        np.testing.assert_array_equal(a.frames, b.frames)
        np.testing.assert_allclose(a.keys, b.keys, rtol=0, atol=5.1e-7)
        np.testing.assert_allclose(a.neutral, b.neutral, rtol=0, atol=5.1e-7)
    # keys.json stores shapes to 6 decimals: decompose with the keys as the command reads them
    weights = api.decompose(from_file, from_cmd)
    assert main(["decompose", str(tmp_path / "t.csv"), "--keys", str(tmp_path / "k.json"),
                 "-o", str(tmp_path / "w.csv")]) == 0
    w = api.Weights.load(tmp_path / "w.csv")
    assert w.names == weights.names == [f"mouth_{i}" for i in range(len(keys.regions[0].keys))]
    np.testing.assert_allclose(w.values, weights.values, rtol=0, atol=5.1e-7)

    # one key set over two "takes" (the clip split in two) is one selection over the concatenation;
    # the keys name each take's own frames
    both = api.select([from_file[:20], from_file[20:]], 4, regions=["mouth"])
    np.testing.assert_array_equal(both.regions[0].frames, keys.regions[0].frames)
    np.testing.assert_array_equal(both.regions[0].takes, (keys.regions[0].frames >= 20).astype(int))


def test_track_frame_range(footage):
    from keyshape import api

    model = api.AppearanceModel.load(footage / "take1_model.npz")
    part = api.track(footage / "take1.mp4", model, start=10, stop=25)
    np.testing.assert_array_equal(part.frame, np.arange(10, 25))
    assert part.success.all()


def test_lazy_api_names_do_not_load_the_stages():
    code = ("import sys, keyshape.base.files, keyshape\n"
            "assert not [m for m in sys.modules if m.startswith(('keyshape.tracker', 'keyshape.decompose', "
            "'keyshape.retarget', 'keyshape.api'))]\n"
            "from keyshape.api import train, Keys\n"
            "assert keyshape.train is train and keyshape.Keys is Keys\n"
            "try:\n    keyshape.nonexistent\nexcept AttributeError:\n    pass\nelse:\n    raise SystemExit(1)\n")
    subprocess.run([sys.executable, "-c", code], check=True)
