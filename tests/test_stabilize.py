"""Head stabilisation on the rigid points (issue 14): RigidStabilizer, KEYS.json's head_pose, the chain."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from keyshape.base.errors import InputError
from keyshape.base.formats.keys import read_keys, read_keys_head_pose
from keyshape.base.formats.tracks import Tracks, read_tracks, write_tracks
from keyshape.base.schemes import load_scheme
from keyshape.cli import main
from keyshape.decompose.regions import head_shapes, model_shapes, stable_pose, to_image
from keyshape.decompose.stabilize import RigidStabilizer, similarity_affines
from toy import mean_face, toy_tracks

SCHEME = load_scheme("contours48")


def _similarity(ang, s, t):
    return np.hstack([s * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]]), np.reshape(t, (2, 1))])


def _apply(a, pts):
    return pts @ a[:2, :2].T + a[:, 2]


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000))
def test_stabiliser_removes_any_per_frame_similarity_and_keeps_the_expression(seed):
    """Each frame of a face whose rigid points never move is turned, scaled and shifted at random: the
    stabilised shapes are the unmoved ones up to one common similarity (the reference's), to 1e-9."""
    rng = np.random.default_rng(seed)
    n = 30
    truth = np.repeat(mean_face()[None], n, axis=0)
    moving = ~np.isin(np.arange(48), SCHEME.rigid)
    truth[:, moving] += rng.normal(scale=6.0, size=(n, moving.sum(), 2))       # any expression at all
    moved = np.stack([_apply(_similarity(rng.uniform(-0.5, 0.5), rng.uniform(0.7, 1.4), rng.uniform(-40, 40, 2)), x)
                      for x in truth])
    stab = RigidStabilizer(SCHEME.rigid).fit(moved)
    out = stab.transform(moved)
    common = similarity_affines(truth[:1, list(SCHEME.rigid)], stab.reference_)[0]
    np.testing.assert_allclose(out, _apply(common, truth), atol=1e-9)
    rig = out[:, list(SCHEME.rigid)]                      # the rigid points stand still in every frame
    np.testing.assert_allclose(rig, np.broadcast_to(rig[0], rig.shape), atol=1e-9)


def test_stabiliser_failed_frames_and_bad_input():
    x = np.repeat(mean_face()[None], 5, axis=0)
    x[2] = np.nan
    stab = RigidStabilizer(SCHEME.rigid).fit(x)
    out = stab.transform(x)
    assert np.isnan(out[2]).all() and np.isfinite(np.delete(out, 2, axis=0)).all()
    np.testing.assert_allclose(stab.correction(x)[2], np.eye(2, 3))
    again = RigidStabilizer.from_dict(json.loads(json.dumps(stab.to_dict())))
    np.testing.assert_allclose(again.transform(x)[[0, 1, 3]], out[[0, 1, 3]], atol=1e-5)
    with pytest.raises(InputError, match="coincide"):
        RigidStabilizer([10, 14]).fit(np.zeros((3, 48, 2)))
    with pytest.raises(InputError, match="two or more distinct"):
        RigidStabilizer([10]).fit(x)
    with pytest.raises(InputError, match="do not have the rigid points"):
        RigidStabilizer([10, 60]).fit(x)
    with pytest.raises(InputError, match="no successful frame"):
        RigidStabilizer(SCHEME.rigid).fit(np.full((3, 48, 2), np.nan))


def _expression_biased_tracks(seed=0, with_exact=False):
    """Toy tracks whose pose takes up part of the expression, as a whole-face tracker's does: the image
    points are right, the pose turns, scales and shifts with the mouth's and brows' activity."""
    tracks, truth = toy_tracks(400, noise_px=0.3, rng=seed, return_truth=True)
    shapes = truth["shapes"]
    act = np.linalg.norm(shapes - shapes.mean(0), axis=2)
    mouth, brows = act[:, 28:48].mean(1), act[:, 0:10].mean(1)
    z = lambda a: (a - a.mean()) / a.std()  # noqa: E731
    err = np.stack([_similarity(0.05 * z(brows)[t], 1 + 0.03 * z(mouth)[t], [2.0 * z(mouth)[t], -3.0 * z(brows)[t]])
                    for t in range(tracks.n_frames)])
    lin = np.einsum("tij,tjk->tik", tracks.pose[:, :, :2], err[:, :, :2])
    pose = np.concatenate([lin, (np.einsum("tij,tj->ti", tracks.pose[:, :, :2], err[:, :, 2])
                                 + tracks.pose[:, :, 2])[..., None]], axis=2)
    biased = Tracks(tracks.frame, tracks.time, tracks.confidence, tracks.success, tracks.points, pose)
    return (biased, shapes, tracks) if with_exact else (biased, shapes)


def _aligned_error(est, truth):
    """RMS point error after one common similarity (the frames may differ by the reference's)."""
    a = similarity_affines(np.nanmean(est, 0)[None], np.nanmean(truth, 0))[0]
    return float(np.sqrt(np.nanmean(((_apply(a, est) - truth) ** 2).sum(-1))))


def test_stabilised_shapes_undo_a_pose_that_moves_with_the_expression():
    tracks, truth, exact = _expression_biased_tracks(with_exact=True)
    floor = _aligned_error(model_shapes(exact), truth)     # the 0.3 px noise alone, with the true pose
    tracker_only = _aligned_error(model_shapes(tracks), truth)
    shapes, stab = head_shapes(tracks, SCHEME, "rigid")
    stabilised = _aligned_error(shapes, truth)
    assert tracker_only > 8 * floor                        # the pose's error shows in the shapes
    # what is left is that noise, carried from the four corners to the whole face
    assert stabilised < 1.6 * floor, (stabilised, floor, tracker_only)
    # the stable pose puts the stabilised shapes back where the points are in the image
    back = to_image(shapes, stable_pose(tracks, stab))
    np.testing.assert_allclose(back, tracks.points, atol=1e-6)
    assert head_shapes(tracks, SCHEME, "tracker")[1] is None


@pytest.mark.parametrize("flag,method,tol", [([], "rigid", 1e-5), (["--head-pose", "3d"], "3d", 1e-3)])
def test_select_records_the_head_pose_and_decompose_applies_it(tmp_path, flag, method, tol):
    tracks, _ = _expression_biased_tracks(1)
    tracks.meta = {"model": "sha256:cccc", "scheme": "contours48"}
    write_tracks(tmp_path / "t.csv", tracks)
    assert main(["select", str(tmp_path / "t.csv"), "-k", "6", "--region", "mouth", "--region", "eyes",
                 "-o", str(tmp_path / "k.json"), *flag]) == 0
    head = read_keys_head_pose(tmp_path / "k.json")
    assert head["method"] == method and head["points"] == [10, 14, 18, 22]
    _, _, regs = read_keys(tmp_path / "k.json")
    stable, _ = head_shapes(read_tracks(tmp_path / "t.csv"), SCHEME, head)
    for rk in regs:                                        # each key is its frame in the stabilised head frame
        np.testing.assert_allclose(rk.keys, stable[rk.frames][:, rk.points], atol=tol)
    assert main(["decompose", str(tmp_path / "t.csv"), "--keys", str(tmp_path / "k.json"),
                 "-o", str(tmp_path / "w.csv")]) == 0
    # tracker-pose keys: recorded as such, and decompose follows them
    assert main(["select", str(tmp_path / "t.csv"), "-k", "6", "--region", "mouth", "--head-pose", "tracker",
                 "-o", str(tmp_path / "k2.json")]) == 0
    assert read_keys_head_pose(tmp_path / "k2.json") == {"method": "tracker"}
    _, _, regs2 = read_keys(tmp_path / "k2.json")
    np.testing.assert_allclose(regs2[0].keys, model_shapes(read_tracks(tmp_path / "t.csv"))[regs2[0].frames][
        :, regs2[0].points], atol=1e-5)


def test_stabilised_keys_reconstruct_the_take_better(tmp_path):
    """With a pose that moves with the expression, 6 keys per region reconstruct the take's true
    expressions better from the stabilised shapes than from the tracker's pose alone."""
    from keyshape import api
    tracks, truth = _expression_biased_tracks(2)
    errs = {}
    for head in ("rigid", "tracker"):
        keys = api.select(tracks, 6, "greedy", ["mouth", "eyes"], head=head)
        w = api.decompose(tracks, keys)
        shapes, _ = head_shapes(tracks, SCHEME, keys.head_pose)
        rec = shapes.copy()
        col = 0
        for rk in keys.regions:
            W = w.values[:, col:col + len(rk.keys)]
            rec[:, rk.points] = rk.neutral + np.einsum("tk,kpd->tpd", W, rk.keys - rk.neutral)
            col += len(rk.keys)
        pts = np.concatenate([rk.points for rk in keys.regions])
        errs[head] = _aligned_error(rec[:, pts], truth[:, pts])
    assert errs["rigid"] < 0.6 * errs["tracker"], errs


@pytest.mark.parametrize("entry, message", [
    ({"method": "wobble"}, "expected 'rigid' or 'tracker'"),
    ({"method": "3d", "points": [10, 14]}, "malformed head_pose"),
    ({"method": "rigid", "points": [10, 99], "reference": [[0, 0], [1, 0]]}, "distinct points in 0..47"),
    ({"method": "rigid", "points": [10, 14], "reference": [[0, 0]]}, "must be 2 finite points"),
    ({"method": "rigid", "points": [10, 14], "reference": [[0, 0], [0, 0]]}, "coincide"),
    ({"method": "rigid", "points": [10, 14]}, "malformed head_pose"),
    ({"method": "rigid", "points": [10, 14], "reference": [[0, "x"], [1, 0]]}, "malformed head_pose"),
])
def test_bad_head_pose_entries_are_refused_naming_the_file(tmp_path, entry, message):
    tracks = toy_tracks(60, rng=0)
    write_tracks(tmp_path / "t.csv", tracks)
    assert main(["select", str(tmp_path / "t.csv"), "-k", "3", "--region", "mouth", "-o", str(tmp_path / "k.json")]) == 0
    d = json.loads((tmp_path / "k.json").read_text())
    d["head_pose"] = entry
    (tmp_path / "k.json").write_text(json.dumps(d))
    with pytest.raises(InputError, match=message) as exc:
        read_keys_head_pose(tmp_path / "k.json")
    assert "k.json" in str(exc.value)
    out = tmp_path / "w.csv"
    assert main(["decompose", str(tmp_path / "t.csv"), "--keys", str(tmp_path / "k.json"), "-o", str(out)]) == 2
    assert not out.exists()


def test_old_key_sets_without_head_pose_decompose_as_before(tmp_path):
    tracks = toy_tracks(120, rng=3)
    write_tracks(tmp_path / "t.csv", tracks)
    assert main(["select", str(tmp_path / "t.csv"), "-k", "4", "--region", "mouth", "--head-pose", "tracker",
                 "-o", str(tmp_path / "k.json")]) == 0
    d = json.loads((tmp_path / "k.json").read_text())
    d.pop("head_pose")                                   # a KEYS.json written before the entry existed
    (tmp_path / "k.json").write_text(json.dumps(d))
    assert read_keys_head_pose(tmp_path / "k.json") == {"method": "tracker"}
    assert main(["decompose", str(tmp_path / "t.csv"), "--keys", str(tmp_path / "k.json"),
                 "-o", str(tmp_path / "w.csv")]) == 0
