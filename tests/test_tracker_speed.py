"""The tracker's speed refactors of issues 16 and 26 keep its results: the per-region refinement (each
region alone and the lips together) and the warp helpers against the straightforward code they replaced
(kept here as the reference)."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from keyshape.tracker.eigenpoints import Pyramid, pyramid_level, warp_level, warp_patch_u8
from keyshape.base.geometry import apply_affine
from keyshape.tracker.fitting import Tracker, single_threaded
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


def _read_region_reference(tracker, pyr, pose, rm, patch):
    """Tracker.read_region as it was before issue 16 (matrix products for the 2x2 system)."""
    x0, y0, w, h = rm.box.tolist()
    crop = rm.crop(patch)
    tx = ty = 0.0
    best = None
    lim = 0.08 * tracker.model.face_width
    (a00, a01, a02), (a10, a11, a12) = pose.tolist()
    for it in range(tracker.region_iter + 1):
        if it:
            bx, by = x0 + tx, y0 + ty
            sub = np.array([[a00, a01, a02 + a00 * bx + a01 * by], [a10, a11, a12 + a10 * bx + a11 * by]])
            crop = _warp_reference(pyr, sub, (w, h))
        e, sd = rm.error(crop)
        qe = rm.qt @ e
        r = float(e @ e) - float(qe @ qe)
        if best is not None and r >= best[0]:
            break
        best = (r, (tx, ty), e)
        if it == tracker.region_iter:
            break
        gx, gy = cv2.spatialGradient(np.ascontiguousarray(crop))
        j = np.empty((rm.n_pix, 2))
        j[:, 0] = gx.ravel()[rm.index]
        j[:, 1] = gy.ravel()[rm.index]
        j *= 1.0 / (8.0 * sd)
        qj = rm.qt @ j
        hs = j.T @ j - qj.T @ qj
        g = j.T @ e - qj.T @ qe
        h00, h01, h11 = float(hs[0, 0]) + 1e-6, float(hs[0, 1]), float(hs[1, 1]) + 1e-6
        g0, g1 = float(g[0]), float(g[1])
        det = h00 * h11 - h01 * h01
        if det <= 0:
            break
        s0 = max(-2.0, min(2.0, -(h11 * g0 - h01 * g1) / det))
        s1 = max(-2.0, min(2.0, -(h00 * g1 - h01 * g0) / det))
        tx, ty = max(-lim, min(lim, tx + s0)), max(-lim, min(lim, ty + s1))
    _, t, e = best
    c = rm.pinv_i @ e
    return (rm.mean_l + rm.ul @ c).reshape(-1, 2) + np.array(t), float(c @ (c / rm.variance)) / len(c)


def _read_lips_reference(tracker, pyr, pose, rms, patch):
    """Tracker.read_lips as it was before issue 26's one-product step (the normalised errors and the Jacobian
    rows formed, one product per block); returns the points and the largest ``mean c²/λ``."""
    n = len(rms)
    npar = 2 * n + 2
    lim = 0.08 * tracker.model.face_width
    slim = tracker.lip_stretch
    lvl = pyramid_level(pyr, pose)
    (a00, a01, a02), (a10, a11, a12) = pose.tolist()
    t = [[0.0, 0.0] for _ in rms]
    st = kt = 0.0
    geo = [(*rm.box.tolist(), rm.box_cx) for rm in rms]
    crops = [rm.crop(patch) for rm in rms]
    best = None
    for it in range(tracker.region_iter + 1):
        if it:
            crops = []
            for (x0, y0, w, h, cx), (tx, ty) in zip(geo, t):
                bx, by = x0 + tx - st * cx, y0 + ty - kt * cx
                crops.append(warp_level(pyr, lvl, [[a00 * (1 + st) + a01 * kt, a01, a00 * bx + a01 * by + a02],
                                                   [a10 * (1 + st) + a11 * kt, a11, a10 * bx + a11 * by + a12]], w, h))
        errs = [rm.error(c) for rm, c in zip(rms, crops)]
        qes = [rm.qt @ e for rm, (e, _) in zip(rms, errs)]
        r = sum(float(e @ e) - float(qe @ qe) for (e, _), qe in zip(errs, qes))
        if best is not None and r >= best[0]:
            break
        best = (r, [list(v) for v in t], st, kt, [e for e, _ in errs])
        if it == tracker.region_iter:
            break
        hess = np.zeros((npar, npar))
        grad = np.zeros(npar)
        for i, (rm, crop, (e, sd), qe) in enumerate(zip(rms, crops, errs, qes)):
            gx, gy = cv2.spatialGradient(np.ascontiguousarray(crop))
            j = np.empty((4, rm.n_pix))
            j[0] = gx.ravel()[rm.index]
            j[1] = gy.ravel()[rm.index]
            j[:2] *= 1.0 / (8.0 * sd)
            j[2] = j[0] * rm.box_xc
            j[3] = j[1] * rm.box_xc
            qj = j @ rm.qt.T
            hr = j @ j.T - qj @ qj.T
            gr = j @ e - qj @ qe
            idx = [2 * i, 2 * i + 1, npar - 2, npar - 1]
            hess[np.ix_(idx, idx)] += hr
            grad[idx] += gr
        hess.flat[::npar + 1] += 1e-6
        ok, sol = cv2.solve(hess, -grad[:, None], flags=cv2.DECOMP_CHOLESKY)
        if not ok:
            break
        sol = sol.ravel().tolist()
        for i, v in enumerate(t):
            v[0] = max(-lim, min(lim, v[0] + max(-2.0, min(2.0, sol[2 * i]))))
            v[1] = max(-lim, min(lim, v[1] + max(-2.0, min(2.0, sol[2 * i + 1]))))
        st = max(-slim, min(slim, st + sol[-2]))
        kt = max(-slim, min(slim, kt + sol[-1]))
    _, t, st, kt, es = best
    out, m2 = [], 0.0
    for rm, e, (x0, y0, w, h, cx), (tx, ty) in zip(rms, es, geo, t):
        c = rm.pinv_i @ e
        m2 = max(m2, float(c @ (c / rm.variance)) / len(c))
        pts = (rm.mean_l + rm.ul @ c).reshape(-1, 2)
        bx = pts[:, 0] - (x0 + cx)
        pts[:, 0] += tx + st * bx
        pts[:, 1] += ty + kt * bx
        out.append(pts)
    return out, m2


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


def test_region_reading_equals_the_reference(model, footage):  # noqa: F811
    frames, _ = footage
    assert model.region_models_
    tr = Tracker(model)
    rng = np.random.default_rng(5)
    worst, moved = 0.0, []
    for frame in frames[:6]:
        tr.reset()
        res = tr.step(frame)
        assert res.success
        for _ in range(3):      # the tracked pose and poses a little off it (other translations per region)
            pose = res.pose + np.hstack([rng.normal(0, 0.01, (2, 2)), rng.normal(0, 1.5, (2, 1))])
            pyr = Pyramid(frame)
            patch = warp_patch_u8(pyr, pose, model.patch_size_)
            for rm in model.region_models_:
                tr._m2 = 0.0
                got = tr.read_region(pyr, pose, rm, patch)
                want, m2 = _read_region_reference(tr, pyr, pose, rm, patch)
                worst = max(worst, float(np.abs(got - want).max()))
                assert tr._m2 == pytest.approx(m2, rel=1e-9)
            lips = [rm for rm in model.region_models_ if tr._is_lip(rm)]
            tr._m2 = 0.0
            got = tr.read_lips(pyr, pose, lips, patch)
            want, m2 = _read_lips_reference(tr, pyr, pose, lips, patch)
            worst = max(worst, max(float(np.abs(g - w).max()) for g, w in zip(got, want)))
            assert tr._m2 == pytest.approx(m2, rel=1e-9)
            moved.append(max(float(np.abs(g - rm.read(rm.crop(patch))).max()) for g, rm in zip(got, lips)))
    assert len(lips) == 2 and np.median(moved) > 0.05          # the lips' boxes had steps to take
    assert worst < 1e-9


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


@pytest.mark.parametrize("lip_stretch", [0.15, 0.0], ids=["lips-together", "lips-apart"])
def test_batched_region_reading_equals_the_per_region_one(model, footage, lip_stretch):  # noqa: F811
    """Issue 26: all regions in one vectorised Gauss-Newton step (``batch_regions=True``) read the points
    the per-region code reads, at the tracked poses and at poses a little off them (other steps per region),
    and track the clip to the same points."""
    frames, truth = footage
    each = Tracker(model, lip_stretch=lip_stretch, region_step="forward")     # as the batched step
    batched = Tracker(model, lip_stretch=lip_stretch, batch_regions=True)
    rng = np.random.default_rng(11)
    diffs, moved, m2s = [], [], []
    for frame in frames:
        each.reset()
        res = each.step(frame)
        assert res.success
        for k in range(4):
            pose = res.pose if k == 0 else res.pose + np.hstack([rng.normal(0, 0.01, (2, 2)),
                                                                 rng.normal(0, 1.5, (2, 1))])
            pyr = Pyramid(frame)
            patch = warp_patch_u8(pyr, pose, model.patch_size_)
            shape, _, _ = each.read(pyr, pose)
            each._m2 = batched._m2 = 0.0
            hit, want = each._read_regions_each(pyr, pose, patch, model.n_points)
            got_hit, got = batched.read_regions(pyr, pose, patch)
            assert np.array_equal(np.flatnonzero(hit), got_hit)
            m2s.append((batched._m2, each._m2))
            diffs.append(np.abs(got - want).max())
            moved.append(np.abs(want - model.landmarks(np.zeros(model.k_))[got_hit]).max())
    diffs = np.array(diffs)
    assert np.median(moved) > 0.5                       # the regions had real work to do
    # the boxes after the first step are sampled by cv2.remap, not cv2.warpAffine: a grey level apart in about
    # one pixel in 10,000 (measured: at most 3e-4 px, median 2e-5 px; identical where no step is taken)
    assert diffs.max() < 0.01 and np.median(diffs) < 1e-4, (diffs.max(), np.median(diffs))
    assert max(abs(x - y) / y for x, y in m2s) < 0.01                 # the shape plausibility read
    with single_threaded():
        a = np.stack([r.points for r in Tracker(model, lip_stretch=lip_stretch, region_step="forward").track(frames)])
        b = np.stack([r.points for r in Tracker(model, lip_stretch=lip_stretch, batch_regions=True).track(frames)])
    assert np.abs(a - b).max() < 0.01
    # and both against the truth the clip was made with
    err = np.linalg.norm(b - truth, axis=-1).mean()
    assert err == pytest.approx(np.linalg.norm(a - truth, axis=-1).mean(), abs=1e-3)


def test_inverse_region_step_tracks_as_well_as_the_forward_one(model, footage):  # noqa: F811
    """Issue 26: the eyes' and brows' inverse-compositional step (precomputed Jacobians) against the
    forward-additive one (the default), on frames with exact landmarks: the same error to a small fraction
    of a pixel, and each region's read at poses a little off the truth pulled back as far."""
    frames, truth = footage
    inv = Tracker(model, region_step="inverse")
    fwd = Tracker(model)
    assert inv.region_step == "inverse" and inv._inverse and not fwd._inverse
    with single_threaded():
        a = np.stack([r.points for r in inv.track(frames)])
        b = np.stack([r.points for r in fwd.track(frames)])
    err_inv = np.linalg.norm(a - truth, axis=-1).mean()
    err_fwd = np.linalg.norm(b - truth, axis=-1).mean()
    # measured: 0.0558 px against 0.0562 px (90 px faces)
    assert err_inv < 1.1 * err_fwd + 0.005, (err_inv, err_fwd)
    rng = np.random.default_rng(2)
    regions = [rm for rm in model.region_models_ if rm.name in inv._inverse]
    assert regions
    gains = []
    for frame, pts in zip(frames, truth):
        res = fwd.step(frame)
        pose = res.pose + np.hstack([np.zeros((2, 2)), rng.normal(0, 1.0, (2, 1))])   # the regions must move
        pyr = Pyramid(frame)
        patch = warp_patch_u8(pyr, pose, model.patch_size_)
        for rm in regions:
            want = apply_affine(res.pose, fwd.read_region(pyr, res.pose, rm, warp_patch_u8(pyr, res.pose, model.patch_size_)))
            got_i = apply_affine(pose, inv.read_region_inverse(pyr, pose, rm, patch))
            got_f = apply_affine(pose, fwd.read_region(pyr, pose, rm, patch))
            gains.append((np.abs(got_i - want).mean(), np.abs(got_f - want).mean()))
    gains = np.array(gains)
    # measured: mean 0.008 px (forward 0.004), at most 0.045 px (forward 0.016), from a 1 px shift
    assert gains[:, 0].mean() < 0.02 and gains[:, 0].max() < 0.1, (gains.mean(0), gains.max(0))
    with pytest.raises(ValueError, match="region_step"):
        Tracker(model, region_step="sideways")


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
