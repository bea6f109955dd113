"""``keyshape synth face3d``: the 3D head's truth against itself (landmarks, head-pose signs, gaze on the
rendered pupils), the written files, determinism, bad options; slow: train + track on it."""
from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pytest
from matplotlib.path import Path as MPath

from keyshape.base.errors import InputError
from keyshape.base.formats.labels import read_labels
from keyshape.base.formats.tracks import read_tracks
from keyshape.base.formats.weights import read_weights
from keyshape.base.schemes import load_scheme
from keyshape.cli import main

pytestmark = pytest.mark.shared_data
SCHEME = load_scheme("contours48")


@pytest.fixture(scope="module")
def facekit(shared_data):
    return shared_data / "ict-facekit"


@pytest.fixture(scope="module")
def sv(facekit):
    from keyshape.data_synth.face3d import Synthetic3D
    return Synthetic3D(facekit, frames=90, seed=2, size=(640, 480))


def _set_frame(sv, t, head=(0.0, 0.0, 0.0), eye=(0.0, 0.0), curves=None):
    """Overwrite frame ``t``'s truth (head angles, both eyes' yaw/pitch, curves) and refresh the landmarks."""
    from keyshape.data_synth.face3d import head_rotation
    p = sv.performance
    p.head_deg[t] = head
    p.translation[t] = 0.0
    p.eye_deg[t] = np.array([eye, eye], float)
    p.curves[t] = 0.0 if curves is None else curves
    sv.rotation = head_rotation(*p.head_deg.T)
    sv.points = sv.project_landmarks()


def _nose_tip(sv, t):
    h = sv.head
    i = int(np.argmax(h.neutral[:9409, 2]))             # the face skin's most forward vertex
    v = h.pose_vertices(sv.performance.curves[t], *sv._eyes(t))
    return sv.project(sv.world(v[[i]], t))[0][0]


def test_landmarks_are_the_projected_posed_mesh(sv):
    """truth = perspective projection of the posed mesh's contours48 vertex mixes; pupils on the turned eyeball."""
    for t in (0, 17, 45, 89):
        v = sv.head.pose_vertices(sv.performance.curves[t], *sv._eyes(t))
        world = sv.world(sv.head.landmark_weights @ v, t)
        xy, _ = sv.project(world)
        rows = [i for i in range(48) if i not in (26, 27)]
        np.testing.assert_allclose(sv.points[t, rows], xy[rows], atol=1e-6)
        # each pupil is the turned eyeball's front: a posed sclera vertex lies within 0.1 cm of it
        pupils3d = sv.landmarks3d()[t]
        for e, row in ((0, 27), (1, 26)):
            shell = v[sv.head.eye_vertices[e]]
            assert np.linalg.norm(shell - pupils3d[row], axis=1).min() < 0.1
            np.testing.assert_allclose(sv.points[t, row], sv.project(sv.world(pupils3d[[row]], t))[0][0], atol=1e-6)


def test_head_angle_signs(sv):
    """yaw > 0: the nose moves image-right (the subject turns to their left); pitch > 0: the nose moves down
    against the eyes; roll > 0: counter-clockwise on the screen (the image-right eye rises)."""
    t = 5
    nose = {}
    for yaw in (-20.0, 0.0, 20.0):
        _set_frame(sv, t, head=(yaw, 0.0, 0.0))
        nose[yaw] = _nose_tip(sv, t)
        eyes_x = sv.points[t, [26, 27], 0].mean()
        if yaw:
            assert np.sign(nose[yaw][0] - eyes_x) == np.sign(yaw)
    assert nose[-20.0][0] < nose[0.0][0] < nose[20.0][0]
    _set_frame(sv, t, head=(0.0, 0.0, 0.0))
    rest = _nose_tip(sv, t)[1] - sv.points[t, [26, 27], 1].mean()
    _set_frame(sv, t, head=(0.0, 12.0, 0.0))
    down = _nose_tip(sv, t)[1] - sv.points[t, [26, 27], 1].mean()
    assert down > rest + 2.0
    _set_frame(sv, t, head=(0.0, 0.0, 8.0))
    left_eye, right_eye = sv.points[t, 10], sv.points[t, 21]        # outer corners, image-left and image-right
    ang = np.degrees(np.arctan2(-(right_eye[1] - left_eye[1]), right_eye[0] - left_eye[0]))
    _set_frame(sv, t, head=(0.0, 0.0, 0.0))
    left_eye, right_eye = sv.points[t, 10], sv.points[t, 21]
    ang0 = np.degrees(np.arctan2(-(right_eye[1] - left_eye[1]), right_eye[0] - left_eye[0]))
    assert 6.0 < ang - ang0 < 10.0


def test_nose_truth_is_the_ibug68_vertices(sv):
    """The truth's nose points (contours48+nose) are the posed mesh's vertices of iBUG-68 points 27, 30, 31, 33,
    35 (the rig landmark correspondence), projected."""
    from keyshape.retarget.rig.model import Rig, rig_landmarks
    h = sv.head
    W68, _ = rig_landmarks(Rig(h.names, h.neutral, np.zeros((0, len(h.neutral), 3)), h.mesh), "ibug68")
    tr = sv.tracks()
    for t in (0, 45):
        v = h.pose_vertices(sv.performance.curves[t], *sv._eyes(t))
        xy, _ = sv.project(sv.world(W68[[27, 30, 31, 33, 35]] @ v, t))
        np.testing.assert_allclose(tr.aux["nose"][t], xy, atol=1e-6)


def test_the_nose_pins_the_head_pitch(sv, tmp_path):
    """The 3D head pose from the truth's points through the tracks CSV (0.5 px noise), against the truth's head
    rotations: with the nose columns pitch stays within 2 degrees (measured: worst 1.4), without them (the eye
    corners' line alone hardly fixes pitch) it is off by more (worst 4.1: 3.5 asserted). Yaw and roll stay within
    4 degrees (worst 2.8 and 2.1 with the nose; 1.2 and 1.2 without: the 3D face keeps the generic face's depths,
    and the nose tip stands farthest out of the eye corners' plane, so a depth unlike this identity's tells most)."""
    from keyshape.api import head as head_api
    from keyshape.base.formats.tracks import Tracks, write_tracks
    from keyshape.data_synth.face3d import head_rotation
    from keyshape.data_synth.face3d import Synthetic3D
    from keyshape.decompose.head3d import euler_angles
    sv = Synthetic3D(sv.head_folder, frames=90, seed=2, size=(640, 480))      # the fixture's, unedited by other tests
    tr = sv.tracks()
    rng = np.random.default_rng(0)
    noisy = Tracks(tr.frame, tr.time, tr.confidence, tr.success, tr.points + rng.normal(0, 0.5, tr.points.shape),
                   tr.pose, {"image_size": list(sv.size)}, {"nose": tr.aux["nose"] + rng.normal(0, 0.5, (90, 5, 2))})
    write_tracks(tmp_path / "t.csv", noisy)
    R = head_rotation(*sv.performance.head_deg.T)
    worst = {}
    for name, t in (("nose", read_tracks(tmp_path / "t.csv")), ("none", noisy[:])):
        if name == "none":
            t.aux = {}
        hd = head_api(t)
        truth = np.degrees(euler_angles(np.einsum("tij,kj->tik", R, R[hd.estimator.zero_frame_])))
        d = hd.angles - truth
        worst[name] = np.abs(d - np.median(d, axis=0)).max(axis=0)
    assert worst["nose"][1] < 2.0 and worst["nose"].max() < 4.0, worst
    assert worst["none"][1] > 3.5, worst


def _pupil_centroid(img, eye_pts):
    """Centroid of the dark (pupil) pixels inside the eye contour."""
    g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(float)
    lo, hi = np.floor(eye_pts.min(0)).astype(int), np.ceil(eye_pts.max(0)).astype(int)
    ys, xs = np.mgrid[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1]
    inside = MPath(eye_pts).contains_points(np.c_[xs.ravel(), ys.ravel()]).reshape(xs.shape)
    patch = g[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1]
    w = np.clip(15.0 - patch, 0, None) * inside                 # the pupil, not the iris or the lash line
    assert w.sum() > 0
    return np.array([(w * xs).sum(), (w * ys).sum()]) / w.sum()


def test_gaze_moves_the_rendered_pupils(sv):
    """eye yaw > 0 moves both dark pupils image-right, pitch > 0 down; each lies on its truth point
    (measured: the dark blob's centroid 0.1-0.6 px across and 1.5-2.2 px below it)."""
    t = 9
    cen = {}
    for eye in ((-20.0, 0.0), (0.0, 0.0), (20.0, 0.0), (0.0, -12.0), (0.0, 12.0)):
        _set_frame(sv, t, eye=eye)
        img = sv.frame(t)
        c = np.array([_pupil_centroid(img, sv.points[t, a:a + 8]) for a in (10, 18)])   # image-left eye first
        # on the truth point: within 1.5 px across; the upper lid hides the pupil's top (and the lid
        # points' chords cut it off the contour), so the visible dark blob sits up to 2-3 px lower
        np.testing.assert_allclose(c[:, 0], sv.points[t, [26, 27], 0], atol=1.5)
        assert (np.abs(c[:, 1] - sv.points[t, [26, 27], 1] - 1.0) < 2.5).all(), (c, sv.points[t, [26, 27]])
        cen[eye] = c
    assert (cen[(20.0, 0.0)][:, 0] - cen[(0.0, 0.0)][:, 0] > 4).all()
    assert (cen[(-20.0, 0.0)][:, 0] - cen[(0.0, 0.0)][:, 0] < -4).all()
    assert (cen[(0.0, 12.0)][:, 1] - cen[(0.0, 0.0)][:, 1] > 2).all()
    assert (cen[(0.0, -12.0)][:, 1] - cen[(0.0, 0.0)][:, 1] < -2).all()


def test_performance_ranges(sv):
    """Blinks close fully, the jaw opens, both smiles, head within the documented ranges."""
    from keyshape.data_synth.face3d import DRIVEN, Synthetic3D
    s = Synthetic3D(sv.head_folder, frames=900, seed=4, size=(320, 240))
    c = s.performance.curves
    for n in ("eyeBlink_L", "eyeBlink_R"):
        assert c[:, DRIVEN.index(n)].max() >= 0.99, n
    assert c[:, DRIVEN.index("jawOpen")].max() >= 0.6
    for n in ("mouthSmile_L", "mouthSmile_R", "browInnerUp_L", "browDown_R"):
        assert c[:, DRIVEN.index(n)].max() >= 0.4, n
    h = s.performance.head_deg
    assert np.abs(h).max(0).tolist() <= [30.0, 15.0, 10.0]
    assert h[:, 0].max() > 20 and h[:, 0].min() < -20


def test_cli_writes_the_take(facekit, tmp_path):
    """60 frames at 320x240 in a few seconds: every file, the curves in the rig's layout, labels = truth."""
    from keyshape.retarget.rig.model import load_rig
    out = tmp_path / "take"
    t0 = time.perf_counter()
    assert main(["synth", "face3d", str(out), "--rig", str(facekit), "--frames", "60", "--size", "320x240",
                 "--labels", "6", "--seed", "1"]) == 0
    dt = time.perf_counter() - t0
    assert dt < 60, dt
    for name in ("video.mp4", "truth.csv", "curves.csv", "head.csv", "truth.json"):
        assert (out / name).is_file(), name
    tr = read_tracks(out / "truth.csv")
    assert tr.points.shape == (60, 48, 2) and tr.success.all()
    assert tr.aux["nose"].shape == (60, 5, 2)             # the nose, in its own columns beside x_0..x_47
    header = (out / "truth.csv").read_text().splitlines()[0].split(",")
    assert sum(h.startswith("x_") for h in header) == 48 and "nose_x_4" in header
    assert (tr.points[..., 0] > 0).all() and (tr.points[..., 0] < 320).all()
    wt = read_weights(out / "curves.csv")
    rig = load_rig(facekit, with_mesh=False)
    assert list(wt.names) == list(rig.names) and wt.weights.shape == (60, rig.n_shapes)
    assert (wt.weights >= 0).all() and (wt.weights <= 1).all()
    head = np.genfromtxt(out / "head.csv", delimiter=",", names=True)
    assert head.dtype.names[:5] == ("frame", "time", "head_yaw_deg", "head_pitch_deg", "head_roll_deg")
    assert len(head) == 60
    frames, shapes = read_labels(out / "labels")
    assert len(frames) == 6
    np.testing.assert_allclose(shapes, np.concatenate([tr.points, tr.aux["nose"]], 1)[frames], atol=1e-3)
    truth = json.loads((out / "truth.json").read_text())
    assert truth["rig_names"] == list(rig.names) and "yaw > 0" in truth["convention"]
    cap = cv2.VideoCapture(str(out / "video.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 60 and int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)) == 320


def test_labels_include_blink_and_open_mouth(sv):
    from keyshape.data_synth.face3d import DRIVEN, Synthetic3D
    s = Synthetic3D(sv.head_folder, frames=300, seed=0, size=(320, 240))
    idx = s.label_frames(12)
    c = s.performance.curves
    assert len(set(idx.tolist())) == 12
    assert c[idx, DRIVEN.index("jawOpen")].max() >= 0.9 * c[:, DRIVEN.index("jawOpen")].max()
    for n in ("eyeBlink_L", "eyeBlink_R"):
        assert c[idx, DRIVEN.index(n)].max() >= 0.9


def test_same_seed_same_take(sv):
    from keyshape.data_synth.face3d import Synthetic3D
    a = Synthetic3D(sv.head_folder, frames=20, seed=3, size=(320, 240))
    b = Synthetic3D(sv.head_folder, frames=20, seed=3, size=(320, 240))
    c = Synthetic3D(sv.head_folder, frames=20, seed=4, size=(320, 240))
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.frame(7), b.frame(7))
    assert np.abs(a.points - c.points).max() > 1.0


@pytest.mark.parametrize("argv, message", [
    (["--frames", "0"], "frames"),
    (["--size", "10x10"], "size"),
    (["--labels", "99", "--frames", "10"], "labels"),
    (["--fps", "-1"], "fps"),
    (["--rig", "/nonexistent/ict"], "rig"),
])
def test_bad_options_fail_in_one_line(facekit, tmp_path, capsys, argv, message):
    out = tmp_path / "o"
    args = ["synth", "face3d", str(out)] + (["--rig", str(facekit)] if "--rig" not in argv else []) + argv
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
    assert not out.exists()


def test_not_an_ict_folder(tmp_path):
    from keyshape.data_synth.face3d import check_facekit
    with pytest.raises(InputError, match="ICT-FaceKit"):
        check_facekit(tmp_path)


@pytest.fixture(scope="module")
def take_3d(facekit, tmp_path_factory):
    """A 300-frame 3D take (seed 0, 12 labels): :func:`synthesize`'s paths."""
    from keyshape.data_synth.face3d import synthesize
    return synthesize(tmp_path_factory.mktemp("take3d") / "t", facekit, frames=300, seed=0, labels=12)


@pytest.fixture(scope="module")
def tracked_3d_take(take_3d, tmp_path_factory):
    """The normal train + track chain on :func:`take_3d`: (tracks, truth, model)."""
    from keyshape.tracker.commands import fit_model, track_video
    tmp = tmp_path_factory.mktemp("track3d")
    out = take_3d
    model = fit_model(out["video"], out["labels"], "contours48")
    track_video(out["video"], model, tmp / "tracks.csv", show_progress=False)
    return read_tracks(tmp / "tracks.csv"), read_tracks(out["truth"]), model


@pytest.mark.slow
def test_tracker_on_the_3d_take(tracked_3d_take):
    """The normal train + track chain on a 300-frame 3D take: mean NME < 0.02, nothing lost; the take's labels
    carry the nose, so the model tracks it too (its own columns, mean error < 0.03 inter-ocular)."""
    tr, truth, model = tracked_3d_take
    iod = SCHEME.interocular_distance(truth.points)
    nme = np.linalg.norm(tr.points - truth.points, axis=-1).mean(1) / iod
    assert tr.success.all()
    assert np.nanmean(nme) < 0.02, np.nanmean(nme)
    nose = np.linalg.norm(tr.aux["nose"] - truth.aux["nose"], axis=-1).mean(1) / iod
    assert model.scheme_.name == "contours48+nose" and np.nanmean(nose) < 0.03, np.nanmean(nose)


@pytest.mark.slow
def test_centred_eye_regions_read_the_lids_at_true_size_on_the_3d_take(take_3d, tracked_3d_take, tmp_path):
    """``AppearanceModel(centre_eyes=True)`` (issue 23): the eye regions trained on crops that follow each
    eye's centroid, the tracker's box alignment reading the eye's displacement. On the same 300-frame take
    and labels as the default chain, each eye's lid gap (inter-ocular units) follows the truth's with
    r >= 0.9 and a gain (least-squares slope on the truth) within 0.85-1.15. Measured: r 0.959 / 0.926,
    gain 0.93 / 0.88 (the default model: r 0.913 / 0.909, gain 0.82 / 0.81); NME 0.0086 (default 0.0091)."""
    from keyshape.base.formats.video import VideoReader
    from keyshape.tracker.commands import track_video
    from keyshape.tracker.eigenpoints import AppearanceModel
    tr0, truth, model0 = tracked_3d_take
    frames, shapes = read_labels(take_3d["labels"])
    images = VideoReader(take_3d["video"], gray=True).read_frames(frames)
    model = AppearanceModel(model0.scheme_, rng=0, centre_eyes=True).fit(list(images), shapes)
    track_video(take_3d["video"], model, tmp_path / "tracks.csv", show_progress=False)
    tr = read_tracks(tmp_path / "tracks.csv")
    iod = SCHEME.interocular_distance(truth.points)
    nme = np.linalg.norm(tr.points - truth.points, axis=-1).mean(1) / iod
    nme0 = np.linalg.norm(tr0.points - truth.points, axis=-1).mean(1) / iod
    assert tr.success.all() and np.nanmean(nme) < np.nanmean(nme0), (np.nanmean(nme), np.nanmean(nme0))
    for name, (a, b) in {"right lids": (12, 16), "left lids": (20, 24)}.items():
        t = np.linalg.norm(truth.points[:, a] - truth.points[:, b], axis=-1) / iod
        r = np.linalg.norm(tr.points[:, a] - tr.points[:, b], axis=-1) / iod
        corr, gain = np.corrcoef(t, r)[0, 1], np.polyfit(t, r, 1)[0]
        assert corr >= 0.9 and 0.85 <= gain <= 1.15, (name, corr, gain)


@pytest.mark.slow
def test_the_lips_shape_fit_reads_the_mouths_opening_at_true_size_on_the_3d_take(tracked_3d_take):
    """Issue 40 item 1: with the lips' shape fitted by analysis by synthesis after the eigen-points reading
    (``AppearanceModel(lip_refine=True)``, the default), the inner lips' gap (inter-ocular units) follows the
    truth's with r >= 0.95 and a gain within 0.85-1.15 on the 300-frame take (the reading alone: r 0.939,
    gain 0.75, ``test_tracker_reads_openings_at_true_size_on_the_3d_take``'s figures before it)."""
    tr, truth, model = tracked_3d_take
    assert model.lip_refiner_ is not None
    iod = SCHEME.interocular_distance(truth.points)
    t = np.linalg.norm(truth.points[:, 42] - truth.points[:, 46], axis=-1) / iod
    r = np.linalg.norm(tr.points[:, 42] - tr.points[:, 46], axis=-1) / iod
    corr, gain = np.corrcoef(t, r)[0, 1], np.polyfit(t, r, 1)[0]
    assert corr >= 0.95 and 0.85 <= gain <= 1.15, (corr, gain)


@pytest.mark.slow
@pytest.mark.xfail(reason="issue 23: the tracker reads the lids' openings at 0.77-0.78 of their true size on "
                          "the 3D take (bench/synth3d_tracker_diag.py); the inner lips' now pass (issue 40)")
def test_tracker_reads_openings_at_true_size_on_the_3d_take(tracked_3d_take):
    """The inner lips' gap and each eye's lid gap (inter-ocular units) follow the truth's with r >= 0.95 and
    a gain (least-squares slope of the tracked on the truth) within 0.85-1.15: what jawOpen and the blinks
    are read from. Measured before the lips' shape fit (issue 40): inner lips r 0.925 gain 0.73, lids r 0.913
    / 0.905, gain 0.77 / 0.78 (the readings shrink toward the labelled frames' mean: a closed mouth reads a
    little open, a wide one less open); the lips now pass
    (:func:`test_the_lips_shape_fit_reads_the_mouths_opening_at_true_size_on_the_3d_take`), the lids not."""
    tr, truth, _ = tracked_3d_take
    iod = SCHEME.interocular_distance(truth.points)
    for name, (a, b) in {"inner lips": (42, 46), "right lids": (12, 16), "left lids": (20, 24)}.items():
        t = np.linalg.norm(truth.points[:, a] - truth.points[:, b], axis=-1) / iod
        r = np.linalg.norm(tr.points[:, a] - tr.points[:, b], axis=-1) / iod
        corr, gain = np.corrcoef(t, r)[0, 1], np.polyfit(t, r, 1)[0]
        assert corr >= 0.95 and 0.85 <= gain <= 1.15, (name, corr, gain)
