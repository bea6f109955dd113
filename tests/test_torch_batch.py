"""The batched torch/kornia tracker (issue 16 item 5) against the CPU tracker, on CPU torch.

Skipped where torch or kornia is not installed (the ``keyshape[torch]`` extra).
"""
from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="torch not installed (pip install keyshape[torch])")
pytest.importorskip("kornia", reason="kornia not installed (pip install keyshape[torch])")

from keyshape.base.errors import InputError, KeyshapeError  # noqa: E402
from keyshape.base.geometry import apply_affine  # noqa: E402
from keyshape.tracker import torch_batch as tb  # noqa: E402
from keyshape.tracker.eigenpoints import Pyramid, warp_patch_u8  # noqa: E402
from keyshape.tracker.fitting import Tracker  # noqa: E402


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.formats.video import VideoReader
    from keyshape.data_synth.video import synthesize
    from keyshape.tracker.commands import fit_model

    out = synthesize(tmp_path_factory.mktemp("torch_clip"), frames=40, seed=0)
    model = fit_model(out["video"], out["labels"], n_morphs=40)
    model.lip_refiner_ = None                  # the torch path reads the whole-face model only: no lips' fit
    frames = np.stack([f for _, f in VideoReader(out["video"])])
    tracker = Tracker(model, region_iter=-1)
    results = [tracker.step(f, i) for i, f in enumerate(frames)]
    assert all(r.success for r in results)
    return {"model": model, "frames": frames, "video": out["video"], "truth": read_tracks(out["truth"]).points,
            "cpu_points": np.stack([r.points for r in results]), "poses": np.stack([r.pose for r in results])}


def test_gray_and_pyramid_are_opencvs_bit_for_bit():
    rng = np.random.default_rng(3)
    frames = rng.integers(0, 256, (3, 131, 97, 3), dtype=np.uint8)          # odd sizes: edge handling
    fr = tb._Frames(torch, frames, torch.device("cpu"))
    assert fr.n_levels == len(Pyramid(frames[0]))
    for lvl in range(fr.n_levels):
        want = np.stack([Pyramid(f)[lvl] for f in frames])
        np.testing.assert_array_equal(fr.level(lvl)[:, 0].numpy(), want)


def test_kornia_warp_matches_cv2_patch_to_a_grey_level(clip):
    m = clip["model"]
    frames, poses = clip["frames"][:8], clip["poses"][:8].copy()
    poses[4:, :, :2] *= 2.5                 # a zoomed-out face: pyramid level 1 or 2 for these frames
    fr = tb._Frames(torch, frames, torch.device("cpu"))
    got = tb._warp(torch, None, fr, torch.as_tensor(poses), m.patch_size_).numpy()
    want = np.stack([warp_patch_u8(Pyramid(f), p, m.patch_size_) for f, p in zip(frames, poses)])
    diff = np.abs(got - want)
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3


def test_read_batch_gives_the_cpu_reading(clip):
    m, frames, poses = clip["model"], clip["frames"], clip["poses"]
    pts, res = tb.read_batch(m, frames, poses)
    tracker = Tracker(m, region_iter=-1)
    cpu = [tracker.read(Pyramid(f), p) for f, p in zip(frames, poses)]
    cpu_pts = np.stack([c[1] for c in cpu])
    err = np.abs(pts - cpu_pts)
    assert err.max() < 0.05 and err.mean() < 1e-3, (err.max(), err.mean())   # measured: 7e-4 and 2e-5
    np.testing.assert_allclose(res, [c[2] for c in cpu], rtol=0.02, atol=1e-4)
    # gray frames read the same as BGR ones
    gray = np.stack([cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames[:4]])
    np.testing.assert_allclose(tb.read_batch(m, gray, poses[:4])[0], pts[:4], atol=5e-3)   # another crop: float32 offsets
    # frames already on the device (a tensor) are used whole, not cropped
    np.testing.assert_allclose(tb.read_batch(m, torch.from_numpy(frames[:4]), poses[:4])[0], pts[:4], atol=5e-3)


@pytest.mark.parametrize("levels", [(0,), ()])
def test_refine_batch_is_the_cpu_update_per_frame(clip, levels):
    m, frames, poses = clip["model"], clip["frames"], clip["poses"]
    rng = np.random.default_rng(1)
    start = np.concatenate([poses[:1], poses[:-1]])
    start[:, :, 2] += rng.uniform(-1.5, 1.5, (len(start), 2))         # the update has real work to do
    got, its = tb.refine_batch(m, frames, start, levels=levels)
    tracker = Tracker(m, region_iter=-1)
    cpu = [tracker.align(Pyramid(f), p, levels) for f, p in zip(frames, start)]
    ref = m.reference_
    moved = np.stack([np.abs(apply_affine(c[0], ref) - apply_affine(s, ref)).max() for c, s in zip(cpu, start)])
    assert np.median(moved) > 0.5
    diff = np.stack([np.abs(apply_affine(g, ref) - apply_affine(c[0], ref)).max() for g, c in zip(got, cpu)])
    assert diff.max() < 0.05, diff.max()      # measured: ~5e-3 at most
    assert np.mean(its == np.array([c[1] for c in cpu])) > 0.8


def test_track_batch_matches_the_cpu_tracker_against_ground_truth(clip):
    from keyshape.base.schemes import load_scheme

    truth = clip["truth"]
    iod = load_scheme("contours48").interocular_distance(truth)[:, None]
    pts, poses, res, ok = tb.track_batch(clip["video"], clip["model"], batch=16)
    assert pts.shape == truth.shape and poses.shape == (len(truth), 2, 3) and ok.all()
    nme_batch = np.mean(np.linalg.norm(pts - truth, axis=-1) / iod)
    nme_cpu = np.mean(np.linalg.norm(clip["cpu_points"] - truth, axis=-1) / iod)
    assert nme_batch < 1.1 * nme_cpu + 1e-4, (nme_batch, nme_cpu)     # measured: 0.00131 both
    assert np.abs(pts - clip["cpu_points"]).max() < 0.5
    # frames given as arrays, a start pose given: the same result
    pts2 = tb.track_batch(iter(clip["frames"]), clip["model"], batch=16, start_pose=poses[0])[0]
    assert np.abs(pts2 - pts).max() < 0.05


def test_bad_input_and_missing_extra(clip, monkeypatch):
    m = clip["model"]
    with pytest.raises(InputError, match="poses"):
        tb.read_batch(m, clip["frames"][:2], np.zeros((3, 2, 3)))
    with pytest.raises(InputError, match="uint8"):
        tb.read_batch(m, clip["frames"][:2].astype(np.float32), clip["poses"][:2])
    with pytest.raises(InputError, match="batch"):
        tb.track_batch(iter(clip["frames"]), m, batch=0)
    monkeypatch.setitem(sys.modules, "kornia", None)
    with pytest.raises(KeyshapeError, match=r"pip install keyshape\[torch\]"):
        tb.read_batch(m, clip["frames"][:2], clip["poses"][:2])
