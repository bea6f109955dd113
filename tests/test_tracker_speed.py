"""The tracker's speed work keeps its results: the compiled per-frame step (issue 40) against stored readings of
the numpy step it replaced, the kernels' sampling against OpenCV's, their disk cache, and the warp helpers
against the straightforward code they replaced (issue 16)."""
from __future__ import annotations

import copy
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from keyshape.tracker.eigenpoints import Pyramid, pyramid_level, warp_level, warp_patch_u8
from keyshape.tracker.fitting import Tracker, _RegionTables, single_threaded
from keyshape.tracker.kernels import sample_affine
from test_tracker import footage, model  # noqa: F401  (module fixtures)


def _warp_reference(pyramid, image_from_model, size):
    """warp_patch_u8 as it was before issue 16 (one function, numpy affine arithmetic)."""
    sw, sh = (size, size) if isinstance(size, int) else (int(size[0]), int(size[1]))
    a = np.asarray(image_from_model, np.float64)
    scale = math.sqrt(abs(a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]))
    lvl = 0
    if scale > 1.5:
        lvl = min(max(int(math.floor(math.log2(scale / 1.5))) + 1, 0), len(pyramid) - 1)
    if lvl:
        f = 0.5 ** lvl
        a = a * f
        a[:, 2] += 0.5 * f - 0.5
    return cv2.warpAffine(pyramid[lvl], a, (sw, sh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


def test_warp_level_is_bit_identical_to_the_old_warp():
    rng = np.random.default_rng(3)
    frame = cv2.GaussianBlur(rng.integers(0, 256, (480, 640), dtype=np.uint8), (5, 5), 1.5)
    levels = set()
    for _ in range(200):
        s, ang = rng.uniform(0.4, 6.0), rng.uniform(-0.5, 0.5)
        lin = s * np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
        lin[0] *= rng.uniform(0.85, 1.15)
        a = np.hstack([lin, rng.uniform([-50, -50], [600, 450])[:, None]])
        size = (int(rng.integers(5, 100)), int(rng.integers(5, 100)))
        pyr = Pyramid(frame)
        lvl = pyramid_level(pyr, a)
        levels.add(lvl)
        got = warp_patch_u8(pyr, a, size)
        assert np.array_equal(got, warp_level(pyr, lvl, a.tolist(), *size))
        assert np.array_equal(got, _warp_reference(Pyramid(frame), a, size))
    assert levels >= {0, 1, 2}
    # a NaN, an infinity or an absurd value anywhere in the affine: a blank patch, not a crash (cv2.warpAffine
    # kills the process on a coefficient of 1e30 or an infinity, seen with OpenCV 5.1)
    pyr = Pyramid(frame)
    for k in range(6):
        for bad in (math.nan, math.inf, -math.inf, 1e30):
            a = np.array([[1.1, 0.1, 200.0], [-0.1, 1.1, 150.0]])
            a.flat[k] = bad
            out = warp_level(pyr, 0, a.tolist(), 20, 20)
            assert out.shape == (20, 20) and out.dtype == np.uint8 and not out.any()


REFERENCE = Path(__file__).parent / "data" / "tracker_step_reference.npz"


def _read_group(tr, rms, stretch, pyr, pose, patch):
    """One group of ``tr.read_regions`` alone (a region, or the lips together with ``stretch``): each region's
    model-frame points at ``pose``."""
    group = (rms, max(tr.region_steps.get(rm.name, tr.region_iter) for rm in rms), stretch)
    tb = _RegionTables([group], 0.08 * tr.model.face_width, tr.lip_stretch, tr.model.n_points)
    pts = tr._run_tables(tb, pyr, pose, patch)
    return [pts[i, :len(rm.points)].copy() for i, rm in enumerate(rms)]


def _reference_cases(tracking_model, frames, poses=None):
    """What ``tests/data/tracker_step_reference.npz`` holds, computed by the tracker under test: the track of
    ``frames`` then ``frames`` reversed (points, poses, residuals), and at ``poses`` (3 per frame of ``frames[:6]``,
    the tracked poses moved by a little noise: drawn here when None) each region's reading
    (each alone, the eyes and brows in the model's order), the lips' (together), the largest shape
    plausibility, the polished pose and the global reading (``read``'s shape and residual)."""
    out = {}
    tr = Tracker(tracking_model)
    seq = list(frames) + list(frames[::-1])
    res = [tr.step(f, i) for i, f in enumerate(seq)]
    out["track_points"] = np.stack([r.points for r in res])
    out["track_poses"] = np.stack([r.pose for r in res])
    out["track_residuals"] = np.array([r.residual for r in res])
    if poses is None:
        rng = np.random.default_rng(5)
        poses = np.stack([out["track_poses"][k] + np.hstack([rng.normal(0, 0.01, (2, 2)), rng.normal(0, 1.5, (2, 1))])
                          for k in range(6) for _ in range(3)])
    out["poses"] = poses
    tr = Tracker(tracking_model)
    cols = {k: [] for k in ("region_points", "lip_points", "m2", "polished_poses", "read_shapes", "read_residuals")}
    alone = [rm for rm in tracking_model.region_models_ if not tr._is_lip(rm)]
    lips = [rm for rm in tracking_model.region_models_ if tr._is_lip(rm)]
    for j, pose in enumerate(poses):
        pyr = Pyramid(frames[j // 3])
        patch = warp_patch_u8(pyr, pose, tracking_model.patch_size_)
        tr._m2 = 0.0
        cols["region_points"].append(np.concatenate([_read_group(tr, [rm], False, pyr, pose, patch)[0]
                                                     for rm in alone]))
        cols["lip_points"].append(np.concatenate(_read_group(tr, lips, True, pyr, pose, patch)))
        cols["m2"].append(tr._m2)
        tr._polished = None
        cols["polished_poses"].append(tr.polish(Pyramid(frames[j // 3]), pose)[0])
        tr._polished = None
        shape, _, r = tr.read(Pyramid(frames[j // 3]), pose)
        cols["read_shapes"].append(shape)
        cols["read_residuals"].append(r)
    out.update({k: np.array(v) for k, v in cols.items()})
    return out


def test_the_compiled_step_reads_what_the_numpy_step_read(model, footage, monkeypatch):  # noqa: F811
    """Issue 40: the compiled per-frame step (``keyshape.tracker.kernels``) against the numpy and OpenCV step it
    replaced. ``tests/data/tracker_step_reference.npz`` was written by that step (commit 16c7cab, the last before
    the kernels) with :func:`_reference_cases` on this module's fixtures, its polish's products taken in double
    precision (its ``_Level.rows32``, ``x32``, ``y32`` as float64; the kernels' sums are double); it is not
    regenerated from the code under test. In single precision, as it ran, that step's track of these frames
    moves by up to 0.034 px from its own double-precision one (a near tie of a kept or undone polish step
    decided the other way); the kernels' track is within 0.01 px of the double-precision one.

    At the same pose, each region's reading, the lips', the global reading and the polished pose are within
    a thousandth of a pixel (the rounding of sums, and one grey level in about 50,000 sampled pixels: the
    boxes are sampled by the kernel, not ``cv2.warpAffine``). The old step had no fit of the lips' shape after
    the reading (``AppearanceModel.lip_refiner_``, issue 40 item 1), so the model here is without it, and each
    frame started from the previous frame's pose (no carried motion, ``Tracker.MOTION_CARRY``), so its track
    is made that way."""
    frames, _ = footage
    want = np.load(REFERENCE)
    monkeypatch.setattr(Tracker, "MOTION_CARRY", 0.0)
    bare = copy.copy(model)
    bare.lip_refiner_ = None
    with single_threaded():
        got = _reference_cases(bare, frames, want["poses"])
    for key in ("region_points", "lip_points", "read_shapes"):
        assert np.abs(got[key] - want[key]).max() < 0.005, key
    assert np.abs(got["polished_poses"] - want["polished_poses"]).max() < 1e-3
    np.testing.assert_allclose(got["m2"], want["m2"], rtol=0.01)
    np.testing.assert_allclose(got["read_residuals"], want["read_residuals"], rtol=1e-6, atol=1e-9)
    assert np.array_equal(np.isnan(got["track_points"]), np.isnan(want["track_points"]))
    per_frame = np.nan_to_num(np.abs(got["track_points"] - want["track_points"])).max(axis=(1, 2))
    assert per_frame.max() < 0.01, per_frame
    np.testing.assert_allclose(got["track_residuals"], want["track_residuals"], rtol=1e-3, atol=1e-6)


def test_the_kernels_sample_as_opencv_does():
    """The kernels' bilinear sampling against ``cv2.warpAffine`` (``INTER_LINEAR | WARP_INVERSE_MAP``,
    ``BORDER_REPLICATE``): the same grey levels but for a very few one level apart, also across the image's
    border; a NaN, an infinity or an absurd coefficient gives a blank patch."""
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 256, (200, 200), dtype=np.uint8), (5, 5), 1.5)
    off = total = 0
    for _ in range(300):
        s, ang = rng.uniform(0.5, 2), rng.uniform(-0.5, 0.5)
        a = np.array([[s * math.cos(ang), -s * math.sin(ang), rng.uniform(-30, 150)],
                      [s * math.sin(ang), s * math.cos(ang), rng.uniform(-30, 150)]])
        want = cv2.warpAffine(img, a, (50, 40), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)
        got = np.empty((40, 50), np.uint8)
        sample_affine(img, a.ravel(), got)
        d = np.abs(got.astype(int) - want)
        assert d.max() <= 1
        off += int((d > 0).sum())
        total += d.size
    assert off / total < 1e-4, off / total
    for bad in (math.nan, math.inf, 1e30):
        a = np.array([1.0, 0.0, bad, 0.0, 1.0, 10.0])
        got = np.full((8, 8), 7, np.uint8)
        sample_affine(img, a, got)
        assert not got.any()


def test_the_kernels_are_cached_on_disk(tmp_path):
    """The kernels compile once and are cached (``cache=True``): a process given an empty ``NUMBA_CACHE_DIR``
    (where numba caches when the package's own folder is read-only) writes them there, and the next one
    loads them from it."""
    code = ("import numpy as np; from keyshape.tracker.kernels import sample_affine; "
            "out = np.empty((4, 4), np.uint8); sample_affine(np.zeros((9, 9), np.uint8), np.array([1.0, 0, 1, 0, 1, 1]), out); "
            "print(sample_affine.stats.cache_hits)")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    first = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert list(tmp_path.rglob("kernels.sample_affine*.nbi")), first.stderr
    second = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert first.stdout.strip() in ("Counter()", "{}") and "1" in second.stdout, (first.stdout, second.stdout)


def test_single_threaded_restores_the_settings_and_keeps_the_points(model, footage):  # noqa: F811
    frames, _ = footage
    before = cv2.getNumThreads()
    a = Tracker(model)
    b = Tracker(model)
    with single_threaded():
        assert cv2.getNumThreads() == 1
        inside = [a.step(f).points for f in frames[:4]]
    assert cv2.getNumThreads() == before
    outside = [b.step(f).points for f in frames[:4]]
    assert np.abs(np.stack(inside) - np.stack(outside)).max() < 1e-9


def test_read_takes_the_patch_polish_sampled_last_and_tracks_the_same(model, footage):  # noqa: F811
    """Issue 26: where polish() ends on a step it does not keep, read() takes the patch polish() sampled at
    the pose it returns instead of sampling it again; the tracks are the same as with a fresh sample."""
    frames, _ = footage
    seq = [f for f in frames for _ in range(2)]          # each frame twice: polish often ends on a step undone

    class Fresh(Tracker):
        def read(self, pyr, pose):
            self._polished = None                      # always sample the patch again
            return super().read(pyr, pose)

    reused = []

    class Counting(Tracker):
        def read(self, pyr, pose):
            got = self._polished
            reused.append(got is not None and got[0] is pyr and got[1] == pose.tolist())
            return super().read(pyr, pose)

    a, b = Counting(model), Fresh(model)
    for i, f in enumerate(seq):
        ra, rb = a.step(f, i), b.step(f, i)
        assert ra.success == rb.success and ra.residual == rb.residual
        np.testing.assert_array_equal(ra.points, rb.points)
        np.testing.assert_array_equal(ra.pose, rb.pose)
    assert any(reused)                                  # the path was taken (2 of the 20 frames here)
