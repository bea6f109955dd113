"""Eigen-points model, pose recovery, lost-track handling, model files, warping, smoothing, and the
``keyshape train`` / ``keyshape track`` commands with their bad-input errors."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from keyshape.base.files import MANIFEST
from keyshape.cli import main
from keyshape.base.errors import InputError, NotFittedError
from keyshape.tracker.eigenpoints import AppearanceModel
from keyshape.tracker.fitting import Tracker
from keyshape.base.formats.tracks import read_tracks
from keyshape.base.formats.labels import write_labels, write_pts
from keyshape.base.schemes import load_scheme
from keyshape.tracker.smoothing import StreamSmoother
from keyshape.base.formats.video import VideoReader, video_writer
from keyshape.base.geometry import apply_affine, compose_affine, fit_affine, fit_similarity, invert_affine
from keyshape.base.warp import PiecewiseAffine, morph, triangulate

SCHEME = load_scheme("contours48")
H, W = 240, 320


def _layout(rng) -> np.ndarray:
    """48 model points in a 90 x 70 px face box; points 10 and 22 (the inter-ocular pair) far apart."""
    pts = np.column_stack([rng.uniform(-45, 45, 48), rng.uniform(-30, 40, 48)])
    pts[10] = (-40, -20)
    pts[22] = (40, -20)
    return pts


def _texture(rng) -> np.ndarray:
    """Smooth random texture, uint8 (the 'face')."""
    noise = rng.normal(size=(H, W)).astype(np.float32)
    img = cv2.GaussianBlur(noise, (0, 0), 3.0)
    img = (img - img.min()) / (img.max() - img.min())
    return (40 + 180 * img).astype(np.uint8)


@pytest.fixture(scope="module")
def footage():
    """Frames made by warping one texture with known landmarks: expression (mouth-like opening of
    the lower points, brow raise of the upper points) plus a head affine; labels exact by construction."""
    rng = np.random.default_rng(7)
    tex = _texture(rng)
    base = _layout(rng)
    centre = np.array([W / 2, H / 2])
    border = np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1], [W / 2, 0], [W / 2, H - 1],
                       [0, H / 2], [W - 1, H / 2]], float)
    tri = triangulate(np.vstack([base + centre, border]))
    frames, labels = [], []
    for k in range(10):
        opening, raise_ = rng.uniform(0, 1), rng.uniform(0, 1)
        shape = base.copy()
        shape[:, 1] += np.where(base[:, 1] > 10, 10 * opening * (base[:, 1] - 10) / 30, 0)
        shape[:, 1] -= np.where(base[:, 1] < -10, 5 * raise_, 0)
        ang, s = rng.uniform(-0.12, 0.12), rng.uniform(0.9, 1.1)
        rot = s * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
        t = centre + rng.uniform(-20, 20, 2)
        img_pts = shape @ rot.T + t
        src_border = border   # background fixed
        pwa = PiecewiseAffine(np.vstack([img_pts, border]), tri, (H, W))
        frames.append(pwa(tex, np.vstack([base + centre, src_border])))
        labels.append(img_pts)
    return np.stack(frames), np.stack(labels)


@pytest.fixture(scope="module")
def model(footage):
    frames, labels = footage
    return AppearanceModel("contours48", n_morphs=40, rng=0).fit(list(frames), labels)


# --------------------------------------------------------------------------- warp


def test_affine_fits_are_exact():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 2)) * 30
    a = np.array([[1.1, 0.2, 5.0], [-0.1, 0.9, -3.0]])
    np.testing.assert_allclose(fit_affine(src, apply_affine(a, src)), a, atol=1e-10)
    c, s = np.cos(0.3) * 1.7, np.sin(0.3) * 1.7
    sim = np.array([[c, -s, 2.0], [s, c, 7.0]])
    np.testing.assert_allclose(fit_similarity(src, apply_affine(sim, src)), sim, atol=1e-10)
    np.testing.assert_allclose(compose_affine(a, invert_affine(a)), [[1, 0, 0], [0, 1, 0]], atol=1e-12)


def test_piecewise_affine_is_affine_for_an_affine_motion_and_morph_endpoints():
    rng = np.random.default_rng(1)
    img = _texture(rng)[:80, :80]
    pts = np.array([[5, 5], [74, 5], [5, 74], [74, 74], [40, 30], [30, 50]], float)
    tri = triangulate(pts)
    a = np.array([[1.0, 0.05, 2.0], [0.0, 1.0, 1.5]])
    pwa = PiecewiseAffine(pts, tri, (80, 80))
    out = pwa(img, apply_affine(a, pts))
    ref = cv2.warpAffine(img, a, (80, 80), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REPLICATE)
    assert np.abs(out[10:70, 10:70].astype(float) - ref[10:70, 10:70]).max() <= 1.0
    other = pts + rng.normal(size=pts.shape)
    m0, s0 = morph(img, pts, img[::-1], other, 0.0, tri, (80, 80))
    np.testing.assert_allclose(s0, pts)
    np.testing.assert_allclose(m0, img, atol=1e-3)


# --------------------------------------------------------------------------- eigen-points algebra


def test_training_frame_gives_back_its_own_labels(footage):
    """With every component kept, a training image lies in the basis: projection is exact."""
    frames, labels = footage
    full = AppearanceModel("contours48", n_components=1000, n_morphs=20, ridge=0.0, rng=0).fit(list(frames), labels)
    for i in range(len(frames)):
        pts, r = full.predict(frames[i], full.train_poses_[i])
        assert np.abs(pts - labels[i]).max() < 0.05, i
        assert r < 1e-6


def test_default_model_reads_training_labels_within_a_fraction_of_a_pixel(model, footage):
    frames, labels = footage
    errs = [np.linalg.norm(model.predict(f, p)[0] - l, axis=1).mean()
            for f, p, l in zip(frames, model.train_poses_, labels)]
    assert max(errs) < 0.5, errs
    assert 1 <= model.k_ < model.n_samples_
    assert model.explained_variance_ratio_.sum() >= 0.98 - 1e-9


def test_unfitted_model_refuses():
    with pytest.raises(NotFittedError, match="not fitted"):
        AppearanceModel().predict(np.zeros((10, 10), np.uint8), np.eye(2, 3))


def test_fit_checks_shapes(footage):
    frames, labels = footage
    with pytest.raises(InputError, match="expected shape"):
        AppearanceModel("ibug68").fit(list(frames), labels)
    with pytest.raises(InputError, match="frames but"):
        AppearanceModel().fit(list(frames[:3]), labels)


# --------------------------------------------------------------------------- pose recovery and tracking


@pytest.mark.parametrize("affine", [
    np.array([[1.0, 0.0, 6.0], [0.0, 1.0, -4.0]]),
    np.array([[1.05, -0.06, -3.0], [0.06, 1.05, 5.0]]),
    np.array([[0.95, 0.04, 4.0], [-0.02, 1.0, 2.0]]),
], ids=["shift", "rotate-scale", "shear"])
def test_warped_training_frame_recovers_the_affine(model, footage, affine):
    frames, labels = footage
    i = 3
    warped = cv2.warpAffine(frames[i], affine, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    tr = Tracker(model)
    tr.pose = tr.last_good = model.train_poses_[i]           # previous frame: the unwarped one
    res = tr.step(warped)
    assert res.success
    want_pose = compose_affine(affine, model.train_poses_[i])
    np.testing.assert_allclose(res.pose[:, :2], want_pose[:, :2], atol=0.01)
    np.testing.assert_allclose(res.pose[:, 2], want_pose[:, 2], atol=0.5)
    assert np.linalg.norm(res.points - apply_affine(affine, labels[i]), axis=1).mean() < 0.5


def test_first_frame_found_without_a_previous_pose(model, footage):
    frames, labels = footage
    shifted = np.roll(frames[5], (15, -25), axis=(0, 1))
    res = Tracker(model).step(shifted)
    assert res.success
    assert np.linalg.norm(res.points - (labels[5] + [-25, 15]), axis=1).mean() < 1.0


def test_lighting_change_does_not_matter(model, footage):
    frames, labels = footage
    dim = (frames[2].astype(np.float32) * 0.5 + 30).astype(np.uint8)
    tr = Tracker(model)
    tr.pose = tr.last_good = model.train_poses_[2]
    res = tr.step(dim)
    assert res.success
    assert np.linalg.norm(res.points - labels[2], axis=1).mean() < 0.5


def test_lost_frame_is_marked_and_recovered(model, footage):
    frames, labels = footage
    rng = np.random.default_rng(3)
    noise = rng.integers(0, 255, (H, W), dtype=np.uint8)
    tr = Tracker(model)
    seq = [frames[0], frames[1], noise, noise, frames[4], np.roll(frames[6], 30, axis=1)]
    out = list(tr.track(seq))
    assert [r.success for r in out] == [True, True, False, False, True, True]
    assert np.isnan(out[2].points).all() and out[2].confidence == 0.0
    assert np.linalg.norm(out[4].points - labels[4], axis=1).mean() < 1.0
    assert np.linalg.norm(out[5].points - (labels[6] + [30, 0]), axis=1).mean() < 1.0
    assert all(0 < r.confidence <= 1 for r in out if r.success)


def _pan(frames, labels, i, step, n):
    """``n`` frames of training frame ``i`` moving ``step`` (dx, dy) pixels a frame, and their true points."""
    out, truth = [], []
    for k in range(n):
        a = np.array([[1.0, 0, k * step[0]], [0, 1.0, k * step[1]]])
        out.append(cv2.warpAffine(frames[i], a, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
        truth.append(labels[i] + np.array(step) * k)
    return out, np.stack(truth)


def test_a_fast_pan_is_followed_from_the_carried_motion(model, footage, monkeypatch):
    """A face moving 8.5 px a frame: from the third frame on each starts from the last pose moved on by half
    the last motion, 4.3 px short instead of 8.5, where the full-resolution polish alone reaches it (at most
    ``n_polish`` steps); started from the last pose every frame needs the coarse-to-fine alignment. The
    points stay on the truth either way."""
    frames, labels = footage
    seq, truth = _pan(frames, labels, 4, (8.0, -3.0), 10)
    for carry in (Tracker.MOTION_CARRY, 0.0):
        monkeypatch.setattr(Tracker, "MOTION_CARRY", carry)
        tr = Tracker(model)
        res = list(tr.track(seq))
        assert all(r.success for r in res)
        err = np.linalg.norm(np.stack([r.points for r in res]) - truth, axis=-1).mean(1)
        assert err.max() < 0.2, (carry, err)
        fast = [r.iterations <= tr.n_polish for r in res[2:]]
        assert all(fast) if carry else not any(fast), (carry, [r.iterations for r in res])


def test_a_restored_state_continues_as_the_tracker_would(model, footage):
    """:meth:`Tracker.state` holds all a next step starts from, the carried motion included."""
    frames, labels = footage
    seq, _ = _pan(frames, labels, 2, (2.5, 1.0), 8)
    a = Tracker(model)
    first = list(a.track(seq[:4]))
    b = Tracker(model)
    b.restore(a.state())
    assert b._motion is not None and first[-1].success
    for f in seq[4:]:
        ra, rb = a.step(f), b.step(f)
        np.testing.assert_array_equal(ra.points, rb.points)
        np.testing.assert_array_equal(ra.pose, rb.pose)


# --------------------------------------------------------------------------- model files


def test_model_roundtrip(model, footage, tmp_path):
    frames, _ = footage
    path = tmp_path / "m.npz"
    model.save(path)
    back = AppearanceModel.load(path, scheme="contours48")
    for i in (0, 4):
        np.testing.assert_allclose(back.predict(frames[i], model.train_poses_[i])[0],
                                   model.predict(frames[i], model.train_poses_[i])[0], atol=1e-9)


def test_bad_model_files(model, tmp_path):
    good = tmp_path / "m.npz"
    model.save(good)
    with pytest.raises(InputError, match=r"m\.npz.*scheme 'contours48'.*not 'ibug68'"):
        AppearanceModel.load(good, scheme="ibug68")
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(good.read_bytes()[:500])
    with pytest.raises(InputError, match=r"corrupt\.npz: not a keyshape model"):
        AppearanceModel.load(corrupt)
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    with pytest.raises(InputError, match=r"other\.npz: not a keyshape model file \(no format header\)"):
        AppearanceModel.load(other)
    import json

    with np.load(good) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    meta["format_version"] = 99
    arrays["meta"] = np.array(json.dumps(meta))
    future = tmp_path / "future.npz"
    np.savez(future, **arrays)
    with pytest.raises(InputError, match=r"future\.npz: model format version 99 is not supported"):
        AppearanceModel.load(future)
    text = tmp_path / "text.npz"
    text.write_text("hello")
    with pytest.raises(InputError, match=r"text\.npz: not a keyshape model"):
        AppearanceModel.load(text)


# --------------------------------------------------------------------------- smoothing


def smooth(points: np.ndarray, method: str = "none", fps: float = 30.0) -> np.ndarray:
    """Smooth a whole track ``(n_frames, n_points, 2)`` with :class:`StreamSmoother`."""
    s = StreamSmoother(method, fps)
    out = []
    for p in np.asarray(points, np.float64):
        out += [q for q, _ in s.push(p)]
    out += [q for q, _ in s.flush()]
    return np.stack(out) if out else np.asarray(points, np.float64).copy()


@pytest.mark.parametrize("method", ["savgol", "oneeuro"])
def test_smoothing_lags_a_fast_mouth_opening_by_at_most_one_frame(method):
    t = np.arange(40)
    gap = np.where(t < 20, 0.0, 12.0)                      # the mouth snaps open at frame 20
    pts = np.zeros((40, 2, 2))
    pts[:, 1, 1] = gap
    out = smooth(pts, method, fps=30)
    # half-way crossing at most one frame after the raw one, and within 10% by frame 21
    raw_cross = 20
    cross = int(np.argmax(out[:, 1, 1] >= 6.0))
    assert cross - raw_cross <= 1
    assert out[21, 1, 1] >= 0.9 * 12 - 1e-9 or method == "savgol" and out[22, 1, 1] >= 0.9 * 12


def test_savgol_keeps_quadratics_and_nan_gaps():
    t = np.arange(30.0)
    pts = np.stack([0.2 * t ** 2 - t, 3 * t], axis=1)[:, None, :]
    np.testing.assert_allclose(smooth(pts, "savgol"), pts, atol=1e-9)
    pts[10] = np.nan
    out = smooth(pts, "savgol")
    assert np.isnan(out[10]).all()
    np.testing.assert_allclose(np.delete(out, 10, 0), np.delete(pts, 10, 0), atol=1e-9)
    noisy = pts + np.random.default_rng(0).normal(size=pts.shape)
    assert np.nanstd(smooth(noisy, "savgol") - pts) < np.nanstd(noisy - pts)


def test_smoothing_off_by_default_and_bad_name():
    pts = np.random.default_rng(0).normal(size=(5, 3, 2))
    np.testing.assert_array_equal(smooth(pts), pts)
    with pytest.raises(InputError, match="unknown smoothing"):
        StreamSmoother("kalman")


# --------------------------------------------------------------------------- commands and bad input

LABELLED = [0, 2, 4, 6, 8]


@pytest.fixture(scope="module")
def files(footage, tmp_path_factory):
    frames, labels = footage
    d = tmp_path_factory.mktemp("cli")
    video = d / "clip.avi"
    with video_writer(video, 10.0, (frames.shape[2], frames.shape[1])) as w:
        for f in frames:
            w.write(np.repeat(f[:, :, None], 3, axis=2))
    write_labels(d / "labels", LABELLED, labels[LABELLED])
    model = d / "model.npz"
    assert main(["train", str(video), "--labels", str(d / "labels"), "-o", str(model)]) == 0
    return d, video, model, labels


def test_train_and_track(files, capsys):
    d, video, model, labels = files
    out = d / "tracks.csv"
    rc = main(["track", str(video), "--model", str(model), "-o", str(out), "--overlay", str(d / "over.avi"),
               "--quiet"])
    assert rc == 0
    tr = read_tracks(out)
    assert tr.n_frames == len(labels) and tr.success.all()
    err = np.linalg.norm(tr.points - labels, axis=-1).mean(1)
    assert err[LABELLED].max() < 1.5 and err.mean() < 2.0, err
    assert (d / "over.avi").is_file()
    assert "10 frames, 0 lost" in capsys.readouterr().out


def test_video_that_does_not_open(files, tmp_path, capsys):
    d, video, model, _ = files
    bad = tmp_path / "notavideo.mp4"
    bad.write_text("hello")
    assert main(["track", str(bad), "--model", str(model), "-o", str(tmp_path / "t.csv")]) == 2
    assert "notavideo.mp4: cannot open as a video" in capsys.readouterr().err
    assert not (tmp_path / "t.csv").exists()


def test_truncated_video_tracks_up_to_the_break(files, tmp_path, capsys):
    d, video, model, _ = files
    data = video.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) * 6 // 10])
    out = tmp_path / "t.csv"
    rc = main(["track", str(cut), "--model", str(model), "-o", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0, err
    tr = read_tracks(out)
    assert 0 < tr.n_frames < 10
    assert "cut.avi ended after" in err and "truncated" in err


def test_label_count_mismatch_names_the_file(files, tmp_path, capsys):
    d, video, _, labels = files
    lab = tmp_path / "labels"
    write_labels(lab, [0, 2], labels[[0, 2]])
    write_pts(lab / "000004.pts", labels[4][:40])
    assert main(["train", str(video), "--labels", str(lab), "-o", str(tmp_path / "m.npz")]) == 2
    assert "000004.pts: 40 points, expected 48" in capsys.readouterr().err


def test_labels_past_the_end(files, tmp_path, capsys):
    d, video, _, labels = files
    lab = tmp_path / "labels"
    write_labels(lab, [0, 2, 50], labels[[0, 2, 4]])
    assert main(["train", str(video), "--labels", str(lab), "-o", str(tmp_path / "m.npz")]) == 2
    err = capsys.readouterr().err
    assert "labels" in err and "[50]" in err and "10 frames" in err


def test_zero_frame_video(files, tmp_path, capsys):
    d, _, model, _ = files
    empty = tmp_path / "empty.avi"
    with video_writer(empty, 10.0, (320, 240)):
        pass
    assert main(["track", str(empty), "--model", str(model), "-o", str(tmp_path / "t.csv"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "empty.avi" in err and ("no decodable frames" in err or "cannot open" in err)
    assert not (tmp_path / "t.csv").exists()


def test_model_from_another_scheme_or_corrupt(files, tmp_path, capsys):
    d, video, model, _ = files
    from keyshape.base.errors import InputError
    from keyshape.base.formats.model import read_model
    with pytest.raises(InputError, match="model.npz: model was trained in scheme 'contours48'"):
        read_model(model, "ibug68")
    bad = tmp_path / "broken.npz"
    bad.write_bytes(model.read_bytes()[:300])
    assert main(["track", str(video), "--model", str(bad), "-o", str(tmp_path / "t.csv")]) == 2
    assert "broken.npz: not a keyshape model file" in capsys.readouterr().err


def interrupt_at(monkeypatch, at: int) -> None:
    """Make the tracker's step raise KeyboardInterrupt (Ctrl-C, or SIGTERM as keyshape raises it) at frame ``at``."""
    real_step = Tracker.step

    def step(self, frame, index=0):
        if index == at:
            raise KeyboardInterrupt
        return real_step(self, frame, index)

    monkeypatch.setattr(Tracker, "step", step)


def test_ctrl_c_keeps_the_frames_tracked_so_far(files, tmp_path, monkeypatch, capsys):
    d, video, model, _ = files
    interrupt_at(monkeypatch, 4)
    out = tmp_path / "t.csv"
    out.write_text("earlier complete tracks\n")                    # the user's own: replaced only with --overwrite
    assert main(["track", str(video), "--model", str(model), "-o", str(out), "--smooth", "savgol", "--quiet",
                 "--overwrite"]) == 130
    assert "interrupted: tracks written for frames 0-3 only, to " in capsys.readouterr().out
    assert out.read_text() == "earlier complete tracks\n"          # the earlier output is untouched
    part = tmp_path / "t.partial.csv"
    with pytest.raises(InputError, match="partial tracks from an interrupted"):
        read_tracks(part)
    tr = read_tracks(part, accept_partial=True)
    np.testing.assert_array_equal(tr.frame, [0, 1, 2, 3])
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == [MANIFEST]   # no temporaries


def test_an_interruption_stops_the_decode_thread_before_the_caller_sees_it(files, monkeypatch):
    """Ctrl-C or SIGTERM in the tracker's step: by the time the caller holds the interruption (whose
    traceback keeps the tracking loop's frame alive), the decode thread has stopped. Left running to the
    interpreter's exit, a daemon thread inside OpenCV's decoder is ended there in C++ and the process
    aborts (SIGABRT, "FATAL: exception not rethrown") instead of exiting 130 / 143."""
    import threading
    from keyshape.tracker.commands import iter_track
    from keyshape.tracker.eigenpoints import AppearanceModel as Model
    d, video, model, _ = files
    interrupt_at(monkeypatch, 4)
    held = None
    try:
        for _ in iter_track(video, Model.load(model)):
            pass
    except KeyboardInterrupt as exc:
        held = exc                                  # the caller keeps it, as `keyshape track` does
    assert held is not None
    assert not [t for t in threading.enumerate() if t.name == "keyshape-decode"]


def test_prefetched_decode_thread_keeps_order_errors_and_early_stop():
    from keyshape.tracker.commands import _prefetched

    assert list(_prefetched(iter(range(100)), depth=3)) == list(range(100))
    for depth, batch in [(8, 4), (8, 1), (3, 5), (1, 7)]:       # whole lists, a partial last one, batch > depth
        assert list(_prefetched(iter(range(23)), depth=depth, batch=batch)) == list(range(23))
    closed = []

    def gen():
        try:
            for i in range(10):
                yield i
            raise ValueError("broken frame")
        finally:
            closed.append(True)

    got = []
    with pytest.raises(ValueError, match="broken frame"):
        for x in _prefetched(gen(), depth=2):
            got.append(x)
    assert got == list(range(10)) and closed == [True]
    closed.clear()
    for x in _prefetched(gen(), depth=2):
        if x == 3:
            break
    assert closed == [True]  # the producer stopped and closed the generator in its thread


def test_brow_border_is_its_own_and_reads_held_out_brows(footage, tmp_path):
    """``brow_grow`` widens only the brow regions' pixel border (None: ``region_grow``, the earlier
    model); a model trained on 8 frames reads the brows of the 2 held-out ones (their true pose given)
    within 0.3 px of the truth (0.10-0.16 measured); the parameter survives the model file, and files
    written before it existed load with the earlier border."""
    frames, labels = footage
    wide = AppearanceModel("contours48", n_morphs=10, rng=0, brow_grow=0.14).fit(list(frames[:8]), labels[:8])
    old = AppearanceModel("contours48", n_morphs=10, rng=0, brow_grow=None).fit(list(frames[:8]), labels[:8])
    boxes = {m: {r.name: r.box for r in m.region_models_} for m in (wide, old)}
    extra = 2 * (round(64 * 0.14) - round(64 * 0.1))
    for name, box in boxes[wide].items():
        if name.startswith("brow"):
            assert box[2] - boxes[old][name][2] == extra and box[3] - boxes[old][name][3] == extra, name
        else:
            np.testing.assert_array_equal(box, boxes[old][name])
    brows = [i for c, v in SCHEME.contours.items() if c.startswith("brow") for i in v]
    for i in (8, 9):
        pose = fit_affine(wide.reference_, labels[i])
        pts, _ = wide.predict(frames[i], pose)
        assert np.linalg.norm(pts[brows] - labels[i][brows], axis=1).mean() < 0.3, i      # brows rise 5 px
    wide.save(tmp_path / "m.npz")
    assert AppearanceModel.load(tmp_path / "m.npz").brow_grow == 0.14
    mf = wide.to_file()
    del mf.params["brow_grow"]
    assert AppearanceModel.from_file(mf).brow_grow is None


def test_eye_variance_is_the_eye_regions_own_and_survives_the_model_file(footage, tmp_path):
    """``eye_variance`` sets the fraction of variance only the eye regions keep (None: ``variance``, the
    earlier model): more of it keeps more eye components and changes nothing else (the global model and
    every other region are bit-identical); a model keeping it all reads its labelled frames' eyes and
    pupils back within 0.05 model pixels; the parameter survives the model file, and files written before it
    existed load as None."""
    frames, labels = footage
    old = AppearanceModel("contours48", n_morphs=10, rng=0, eye_variance=None).fit(list(frames[:8]), labels[:8])
    more = AppearanceModel("contours48", n_morphs=10, rng=0, eye_variance=0.999).fit(list(frames[:8]), labels[:8])
    np.testing.assert_array_equal(more.components_, old.components_)
    for a, b in zip(old.region_models_, more.region_models_):
        if a.name.startswith("eye"):
            assert len(b.variance) > len(a.variance), a.name
        else:
            np.testing.assert_array_equal(a.components, b.components)
    from keyshape.tracker.eigenpoints import Pyramid, warp_patch
    full = AppearanceModel("contours48", n_morphs=10, ridge=0.0, rng=0, eye_variance=1.0).fit(list(frames[:8]),
                                                                                               labels[:8])
    eyes = {i for c, v in SCHEME.contours.items() if c.startswith(("eye", "pupil")) for i in v}
    rm = {r.name: r for r in full.region_models_ if r.name.startswith("eye")}
    assert eyes == {int(p) for r in rm.values() for p in r.points}
    for i in range(8):
        patch = warp_patch(Pyramid(frames[i]), full.train_poses_[i], full.patch_size_)
        for name, r in rm.items():          # model-frame points against the label's, in model pixels
            assert np.abs(r.read(r.crop(patch)) - full.train_shapes_[i][r.points]).max() < 0.05, (i, name)
    more.save(tmp_path / "m.npz")
    assert AppearanceModel.load(tmp_path / "m.npz").eye_variance == 0.999
    mf = more.to_file()
    del mf.params["eye_variance"]
    assert AppearanceModel.from_file(mf).eye_variance is None


def test_centred_eye_regions_read_their_own_labels_and_survive_the_model_file(footage, tmp_path):
    """``centre_eyes`` (issue 23): the eye regions are trained on crops that follow each eye's centroid.
    With every component kept a training frame is read back exactly (``predict`` places the box at the
    global reading's centroid, the same shift the training crop had); only the eye regions are centred;
    the tracker then aligns their boxes in 4 steps (the other regions 2); the flags survive the model file,
    and files written before them load as not centred."""
    frames, labels = footage
    full = AppearanceModel("contours48", n_components=1000, n_morphs=20, ridge=0.0, rng=0,
                           centre_eyes=True).fit(list(frames), labels)
    assert {r.name for r in full.region_models_ if r.centred} == {"eye_left", "eye_right"}
    for i in range(len(frames)):
        pts, r = full.predict(frames[i], full.train_poses_[i])
        assert np.abs(pts - labels[i]).max() < 0.05, i
    model = AppearanceModel("contours48", n_morphs=10, rng=0, centre_eyes=True).fit(list(frames[:8]), labels[:8])
    tracker = Tracker(model)
    assert tracker.region_iter == 2 and tracker.region_steps == {"eye_left": 4, "eye_right": 4}
    assert Tracker(model, region_iter=1).region_iter == 1 and not Tracker(model, region_iter=1).region_steps
    model.save(tmp_path / "m.npz")
    back = AppearanceModel.load(tmp_path / "m.npz")
    assert back.centre_eyes and [r.centred for r in back.region_models_] == [r.centred for r in model.region_models_]
    np.testing.assert_allclose(back.predict(frames[9], model.train_poses_[0])[0],
                               model.predict(frames[9], model.train_poses_[0])[0], atol=1e-9)
    mf = model.to_file()
    del mf.params["centre_eyes"]
    for r in mf.state["region_models"]:
        del r["centred"]
    old = AppearanceModel.from_file(mf)
    assert not old.centre_eyes and not any(r.centred for r in old.region_models_) and not Tracker(old).region_steps


def test_decode_thread_converts_to_gray_as_the_tracker_does(files, tmp_path):
    """Issue 26: with the decode thread the frames reach the tracker already gray (converted in that
    thread): the same points, poses and kept (colour) frames as the tracker converting them itself."""
    from keyshape.tracker.commands import iter_track
    from keyshape.tracker.defaults import TrackOptions

    d, video, model, labels = files
    tinted = tmp_path / "tinted.avi"
    frames = [f for _, f in VideoReader(video)]
    with video_writer(tinted, 10.0, (frames[0].shape[1], frames[0].shape[0])) as w:
        for f in frames:
            g = f[:, :, 0].astype(np.float64)
            w.write(np.stack([g, 0.8 * g + 20, np.minimum(1.2 * g, 255)], -1).astype(np.uint8))
    model = AppearanceModel.load(model)
    runs = [list(iter_track(tinted, model, TrackOptions(decode_thread=t), keep_frames=True)) for t in (True, False)]
    assert len(runs[0]) == len(runs[1]) == len(frames)
    for (pa, ra, fa), (pb, rb, fb) in zip(*runs):
        assert fa.ndim == 3 and np.array_equal(fa, fb)
        assert ra.success == rb.success and np.array_equal(ra.pose, rb.pose)
        np.testing.assert_array_equal(pa, pb)
    assert sum(r.success for _, r, _ in runs[0]) >= len(frames) - 1


def test_labels_of_another_point_count_are_refused_naming_the_scheme(files, tmp_path, capsys):
    """Labels whose every file has 50 points (neither contours48's 48 nor 53 with its nose points): one line
    naming the folder, both counts the scheme takes, and no model written."""
    d, video, _, labels = files
    lab = tmp_path / "labels"
    wrong = np.concatenate([labels[[0, 2, 4]], labels[[0, 2, 4]][:, :2]], axis=1)
    write_labels(lab, [0, 2, 4], wrong)
    out = tmp_path / "m.npz"
    assert main(["train", str(video), "--labels", str(lab), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "labels of 50 points, expected 48 for scheme 'contours48' (53 with its nose points)" in err
    assert str(lab) in err and not out.exists()


def test_a_frame_left_at_the_generic_shape_is_not_trained_on(files, tmp_path, capsys):
    """A frame where dlib found no face starts from the label page's generic shape (``session.json``'s
    ``no_face``); while its points are still that shape it is not a label: ``train`` leaves it out and says so,
    and refuses a folder of nothing else. Once its points are placed, it is trained on."""
    import json

    from keyshape.tracker.commands import fit_model
    from keyshape.tracker.labelling.prepare import template_points
    _, video, _, labels = files
    d = tmp_path / "labels"
    write_labels(d, LABELLED, labels[LABELLED])
    generic = template_points(SCHEME, W, H)
    write_pts(d / "000008.pts", generic)
    (d / "session.json").write_text(json.dumps({"scheme": "contours48", "video": str(video), "frames": LABELLED,
                                                "no_face": [8]}))
    model = fit_model(video, d)
    assert len(model.train_poses_) == 4
    assert "frames [8] still hold the generic shape" in capsys.readouterr().out
    write_pts(d / "000008.pts", labels[8])                 # placed by hand: a label again
    assert len(fit_model(video, d).train_poses_) == 5
    for f in LABELLED:
        write_pts(d / f"{f:06d}.pts", generic)
    (d / "session.json").write_text(json.dumps({"scheme": "contours48", "video": str(video), "frames": LABELLED,
                                                "no_face": LABELLED}))
    with pytest.raises(InputError, match="every label is still the generic shape"):
        fit_model(video, d)


def test_a_face_mostly_outside_the_picture_is_not_a_reading(model, footage):
    """``Tracker._sane`` refuses a reading with more than ``MAX_OUTSIDE`` (0.4) of the face's points outside the
    picture (a close-up whose face leaves the frame: the points there are the model's guess; docs/tracker.md,
    "Close-ups"), and keeps one with 0.3 outside."""
    frames, labels = footage
    tr = Tracker(model)
    pose = model.train_poses_[4]
    shape = apply_affine(invert_affine(pose), labels[4])           # the model-frame points
    for frac, ok in ((0.0, True), (0.3, True), (0.45, False), (0.7, False)):
        x = np.sort(labels[4][:, 0])
        shift = 0.0 if frac == 0 else W - 0.5 - x[int(round((1 - frac) * len(x))) - 1] + 1e-6
        p = compose_affine(np.array([[1.0, 0, shift], [0, 1.0, 0]]), pose)
        pts = labels[4] + (shift, 0)
        outside = ((pts[:, 0] > W - 0.5) | (pts[:, 0] < -0.5)).mean()
        assert abs(outside - frac) < 0.03, (frac, outside)
        assert tr._sane(p, shape, pts, (H, W)) is ok, frac
