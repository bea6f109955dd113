"""One key set per actor (issue 14): model identity in tracks and KEYS.json, several takes, the actor's neutral."""
from __future__ import annotations

import json

import numpy as np
import pytest

from keyshape.base.formats.keys import read_keys, read_keys_head_pose, read_keys_source
from keyshape.base.formats.weights import read_weights
from keyshape.base.formats.tracks import read_tracks, write_tracks
from keyshape.cli import main
from keyshape.decompose.regions import head_shapes, region_points, relaxed_frame
from toy import toy_tracks
from keyshape.base.schemes import load_scheme

SCHEME = load_scheme("contours48")


def _take(path, seed, model="sha256:aaaa"):
    t = toy_tracks(240, rng=seed)
    t.meta = {"model": model, "scheme": "contours48"} if model else {}
    write_tracks(path, t)
    return path


def test_tracks_metadata_sidecar_roundtrips_and_the_csv_stays_plain(tmp_path):
    import csv
    import warnings

    p = _take(tmp_path / "a.csv", 1)
    # the CSV is what OpenFace-style readers expect: header first, every row numeric
    with open(p) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 240 and float(rows[0]["x_0"]) == pytest.approx(read_tracks(p).points[0, 0, 0], abs=1e-4)
    side = json.loads((tmp_path / "a.meta.json").read_text())
    assert side["model"] == "sha256:aaaa" and side["keyshape_tracks"] == 1
    t = read_tracks(p)
    assert t.meta == {"model": "sha256:aaaa", "scheme": "contours48"} and t.n_frames == 240
    # without metadata: no sidecar, and the stale one keyshape wrote is removed
    q = _take(tmp_path / "a.csv", 1, model=None)
    assert not (tmp_path / "a.meta.json").exists() and read_tracks(q).meta == {}
    np.testing.assert_array_equal(read_tracks(q).points, t.points)
    # a CSV edited after tracking no longer vouches for the model: metadata ignored, with a warning
    p = _take(tmp_path / "b.csv", 1)
    lines = p.read_text().splitlines()
    lines[1] = lines[1].replace(lines[1].split(",")[2], "0.5000", 1)
    p.write_text("\n".join(lines) + "\n")
    with pytest.warns(UserWarning, match="b.meta.json: written for another version of b.csv"):
        assert read_tracks(p).meta == {}
    # a file of that name that keyshape did not write is neither read nor removed
    (tmp_path / "c.meta.json").write_text('{"author": "someone"}')
    r = _take(tmp_path / "c.csv", 1, model=None)
    assert (tmp_path / "c.meta.json").read_text() == '{"author": "someone"}' and read_tracks(r).meta == {}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_tracks(_take(tmp_path / "d.csv", 3))


def test_old_metadata_line_still_reads(tmp_path):
    p = _take(tmp_path / "a.csv", 1, model=None)
    p.write_text('# keyshape-tracks {"model": "sha256:bbbb", "scheme": "contours48"}\n' + p.read_text())
    assert read_tracks(p).meta == {"model": "sha256:bbbb", "scheme": "contours48"}


@pytest.mark.parametrize("flag,method,tol", [([], "rigid", 1e-5), (["--head-pose", "3d"], "3d", 1e-3)])
def test_select_several_takes_records_model_and_takes(tmp_path, flag, method, tol):
    a, b = _take(tmp_path / "a.csv", 1), _take(tmp_path / "b.csv", 2)
    assert main(["select", str(a), str(b), "-k", "6", "--region", "mouth", "-o", str(tmp_path / "k.json"),
                 *flag]) == 0
    src = read_keys_source(tmp_path / "k.json")
    assert src["model"] == "sha256:aaaa" and src["scheme"] == "contours48" and len(src["tracks"]) == 2
    d = json.loads((tmp_path / "k.json").read_text())
    keys = d["regions"]["mouth"]["keys"]
    takes = {k["take"] for k in keys}
    assert takes <= {0, 1}
    _, _, regs = read_keys(tmp_path / "k.json")
    head = read_keys_head_pose(tmp_path / "k.json")          # the key set's stabiliser, fitted on both takes
    assert head["method"] == method and head["points"] == list(SCHEME.rigid)
    shapes = {i: head_shapes(read_tracks(p), SCHEME, head)[0] for i, p in enumerate((a, b))}
    for k, key in zip(keys, regs[0].keys):      # every key is the frame its take and frame number name
        np.testing.assert_allclose(shapes[k["take"]][k["frame"], regs[0].points], key, atol=tol)


def test_select_refuses_takes_of_different_models(tmp_path, capsys):
    a, b = _take(tmp_path / "a.csv", 1), _take(tmp_path / "b.csv", 2, model="sha256:bbbb")
    out = tmp_path / "k.json"
    assert main(["select", str(a), str(b), "-k", "4", "-o", str(out)]) == 2
    assert "different tracker models" in capsys.readouterr().err and not out.exists()


def test_decompose_refuses_keys_of_another_model_unless_allowed(tmp_path, capsys):
    a, b = _take(tmp_path / "a.csv", 1), _take(tmp_path / "b.csv", 2, model="sha256:bbbb")
    assert main(["select", str(a), "-k", "4", "--region", "mouth", "-o", str(tmp_path / "k.json")]) == 0
    out = tmp_path / "w.csv"
    assert main(["decompose", str(b), "--keys", str(tmp_path / "k.json"), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "k.json" in err and "another tracker model" in err and not out.exists()
    assert main(["decompose", str(b), "--keys", str(tmp_path / "k.json"), "--allow-foreign-keys",
                 "-o", str(out)]) == 0
    assert main(["decompose", str(a), "--keys", str(tmp_path / "k.json"), "-o", str(out)]) == 0


def test_neutral_frame_makes_weights_relative_to_the_actor_neutral(tmp_path):
    a = _take(tmp_path / "a.csv", 3)
    t = read_tracks(a)
    assert main(["select", str(a), "-k", "5", "--region", "mouth", "--neutral-frame", "17",
                 "-o", str(tmp_path / "k.json")]) == 0
    _, _, regs = read_keys(tmp_path / "k.json")
    rk = regs[0]
    assert rk.rest_frame == 17
    np.testing.assert_allclose(rk.neutral, head_shapes(t, SCHEME)[0][17, rk.points], atol=1e-5)
    # per-frame NNLS (the default smooth solver lets the neighbours' weights into a frame)
    assert main(["decompose", str(a), "--keys", str(tmp_path / "k.json"), "--solver", "nnls", "--ridge", "0",
                 "-o", str(tmp_path / "w.csv")]) == 0
    _, _, w, _ = read_weights(tmp_path / "w.csv")
    assert np.abs(w[17]).max() < 1e-6                    # the neutral frame has no key weight
    assert main(["select", str(a), "-k", "5", "--region", "mouth", "--neutral-frame", "mean",
                 "-o", str(tmp_path / "m.json")]) == 0
    _, _, regs = read_keys(tmp_path / "m.json")
    np.testing.assert_allclose(regs[0].neutral, np.nanmean(head_shapes(t, SCHEME)[0][:, rk.points], axis=0), atol=1e-5)


def test_relaxed_frame_is_the_mode_of_the_shapes():
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(10, 2))
    frames = rest + 0.01 * rng.normal(size=(300, 10, 2))          # mostly at rest
    frames[::3] += rng.uniform(0.5, 2.0, (100, 1, 1)) * rng.normal(size=(100, 10, 2))   # expressions
    frames[5] = np.nan                                            # a failed frame is never chosen
    i = relaxed_frame(frames)
    assert i % 3 != 0 and np.abs(frames[i] - rest).max() < 0.05


def test_relaxed_frame_prefers_the_face_returned_to_over_a_held_expression():
    # 30 frames of one held expression (no noise: a tight cluster) against 200 relaxed frames
    # spread by tracking noise: the neutral is the relaxed face, not the held expression
    rng = np.random.default_rng(1)
    rest = rng.normal(size=(10, 2))
    held = rest + 0.5 * rng.normal(size=(10, 2))
    frames = np.concatenate([rest + 0.05 * rng.normal(size=(200, 10, 2)),
                             held + 0.002 * rng.normal(size=(30, 10, 2)),
                             rest + rng.uniform(0.3, 1.5, (170, 1, 1)) * rng.normal(size=(170, 10, 2))])
    i = relaxed_frame(frames)
    assert i < 200, i


def test_near_duplicate_keys_are_dropped():
    from keyshape.decompose.regions import near_duplicates
    ref = np.zeros((4, 2))
    keys = np.stack([np.full((4, 2), 1.0), np.full((4, 2), 1.02), np.full((4, 2), -1.0), np.full((4, 2), 2.0)])
    assert near_duplicates(keys, ref, 0.1).tolist() == [0, 2, 3]
    assert near_duplicates(keys, ref, 0.0).tolist() == [0, 1, 2, 3]


def test_select_sheet_shows_the_neutral_and_key_distances(tmp_path):
    from keyshape.decompose.sheet import key_tiles
    a = _take(tmp_path / "a.csv", 4)
    t = read_tracks(a)
    assert main(["select", str(a), "-k", "3", "--region", "mouth", "-o", str(tmp_path / "k.json")]) == 0
    _, _, regs = read_keys(tmp_path / "k.json")
    frames = {int(f): np.zeros((480, 640, 3), np.uint8) for f in t.frame}
    tiles, captions = key_tiles(frames, t, SCHEME, regs, tile_width=120)
    assert captions[0].startswith(f"mouth_neutral  frame {regs[0].rest_frame}")
    assert len(captions) == len(regs[0].keys) + 1 and all(" d=" in c for c in captions[1:])


def test_face_rest_frame_is_relaxed_where_a_region_alone_picks_a_held_expression(tmp_path):
    """The eyes hold a lopsided brow raise, without noise, for 35% of the take while the mouth talks; the
    rest of the time the brows are relaxed (with tracking noise) and so is the mouth. The eyes' own densest
    shape is the held raise; the whole face's is a relaxed frame, and select records it for every region."""
    from keyshape.base.formats.tracks import Tracks
    from keyshape.decompose.regions import face_rest_frame
    from toy import mean_face
    rng = np.random.default_rng(0)
    n = 400
    X = np.repeat(mean_face()[None], n, axis=0)
    held = np.zeros(n, bool)
    held[100:240] = True
    eyes, mouth = region_points(SCHEME, "eyes"), region_points(SCHEME, "mouth")
    X[np.ix_(~held, eyes)] += rng.normal(scale=0.4, size=((~held).sum(), len(eyes), 2))
    X[np.ix_(held, eyes[:5])] += [0.0, -6.0]                       # one brow raised, held exactly
    X[np.ix_(~held, mouth)] += rng.normal(scale=0.4, size=((~held).sum(), len(mouth), 2))
    X[np.ix_(held, mouth)] += rng.normal(scale=6.0, size=(held.sum(), len(mouth), 2))   # talking
    tr = Tracks(np.arange(n), np.arange(n) / 25.0, np.ones(n), np.ones(n, bool), X,
                np.broadcast_to(np.eye(2, 3), (n, 2, 3)).copy())
    assert held[relaxed_frame(X[:, eyes])]                           # the region alone: the held raise
    f = face_rest_frame(tr, X, SCHEME, ["mouth", "eyes"])
    assert not held[f]
    # select does the same on its head-frame shapes (the default head step)
    f = face_rest_frame(tr, head_shapes(tr, SCHEME)[0], SCHEME, ["mouth", "eyes"])
    assert not held[f]
    write_tracks(tmp_path / "t.csv", tr)
    assert main(["select", str(tmp_path / "t.csv"), "-k", "3", "--region", "mouth", "--region", "eyes",
                 "-o", str(tmp_path / "k.json")]) == 0
    _, _, regs = read_keys(tmp_path / "k.json")
    assert {rk.rest_frame for rk in regs} == {f}
