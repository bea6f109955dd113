"""dlib landmarker wrapper: lazy optional import, model lookup, real-frame detection."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from keyshape.base.errors import KeyshapeError


def test_missing_dlib_says_what_to_install(monkeypatch):
    from keyshape.tracker.labelling import dlib_landmarker as dl
    monkeypatch.setitem(sys.modules, "dlib", None)  # import dlib -> ImportError
    with pytest.raises(KeyshapeError, match=r'pip install "keyshape\[label\]"'):
        dl.DlibLandmarker()


def test_missing_models_package_says_what_to_install(monkeypatch):
    from keyshape.tracker.labelling import dlib_landmarker as dl
    monkeypatch.setattr(dl.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(KeyshapeError, match=r'pip install "keyshape\[label\]"'):
        dl.default_model_path()


@pytest.fixture(scope="module")
def landmarker():
    pytest.importorskip("dlib", reason="dlib (keyshape[label]) not installed")
    from keyshape.tracker.labelling.dlib_landmarker import DlibLandmarker
    return DlibLandmarker()


def test_no_face_in_blank_image(landmarker):
    assert landmarker.detect(np.full((200, 200), 128, np.uint8)) is None


def test_real_frame_gives_plausible_68_points(landmarker, shared_data):
    from keyshape.base.formats.video import VideoReader
    frames = VideoReader(shared_data / "video" / "franck.mp4", gray=True).read_frames([0, 100])
    pts = np.stack([landmarker.detect(f) for f in frames])
    assert pts.shape == (2, 68, 2) and np.all(np.isfinite(pts))
    for p in pts:
        io = np.linalg.norm(p[36] - p[45])
        assert 30 < io < 200  # a face in a 360x288 frame
        assert p[36, 0] < p[45, 0]  # image-left eye corner left of image-right
        assert p[8, 1] > p[30, 1] > p[27, 1]  # chin below nose tip below nose bridge
        assert p[19, 1] < p[37, 1] < p[51, 1]  # brow above eye above upper lip
    # same frame twice -> same points (deterministic)
    np.testing.assert_array_equal(landmarker.detect(frames[0]), pts[0])


def test_averaged_prediction_is_closer_to_mediapipe(landmarker, shared_data):
    """The pre-fill's 14-view average has less frame-varying error than one prediction, judged against
    MediaPipe (an independent landmarker) on 60 frames of franck.mp4; and it is mirror-consistent."""
    from keyshape.base.formats.video import VideoReader
    from keyshape.tracker.labelling.dlib_landmarker import IBUG68_MIRROR
    ref = np.load(shared_data / "video" / "references" / "franck_references.npz")
    mp = ref["mediapipe478"].astype(float)
    frames = np.linspace(0, len(mp) - 1, 60).astype(int)
    imgs = VideoReader(shared_data / "video" / "franck.mp4", gray=True).read_frames(frames)
    single, averaged = [], []
    for g in imgs:
        box = landmarker.detect_box(g)
        single.append(landmarker.predict(g, box))
        averaged.append(landmarker.predict_averaged(g, box))
    # eye corners and lids, lip corners and mid points (as shared/tools/real_accuracy.py)
    ib = [36, 39, 42, 45, 48, 54, 51, 57, 62, 66]
    mpi = [33, 133, 362, 263, 61, 291, 0, 17, 13, 14]
    iod = np.linalg.norm(mp[frames, 263] - mp[frames, 33], axis=1)

    def spread(p):
        d = (np.asarray(p)[:, ib] - mp[frames][:, mpi]) / iod[:, None, None]
        d = d - d.mean(0)
        return float(np.sqrt((d ** 2).sum(-1).mean()))

    s1, s2 = spread(single), spread(averaged)
    assert s2 < 0.95 * s1, (s1, s2)
    g = imgs[0]
    box = landmarker.detect_box(g)
    w = g.shape[1]
    a = landmarker.predict_averaged(g, box)
    m = landmarker.predict_averaged(np.ascontiguousarray(g[:, ::-1]),
                                    landmarker._dlib.rectangle(w - 1 - box.right(), box.top(), w - 1 - box.left(),
                                                               box.bottom()))[IBUG68_MIRROR]
    m[:, 0] = w - 1 - m[:, 0]
    np.testing.assert_allclose(a, m, atol=0.05 * np.linalg.norm(a[36] - a[45]))
    assert sorted(IBUG68_MIRROR.tolist()) == list(range(68))


def test_a_close_up_reaching_past_the_frame_is_found_whole(landmarker, shared_data, monkeypatch):
    """A close-up (glasses_rom.mp4 enlarged 1.8 times about its face: the face fills the frame, the forehead and
    chin at or past its edges): the pre-fill's points, against dlib's reference points of the whole frame mapped
    into the close-up, within 0.015 inter-ocular distances on each frame. dlib's detector alone puts frame 120's
    box short of the face (its window cannot leave the image), over 0.04 off; the bordered frame finds it whole."""
    import cv2

    from keyshape.base.formats.video import VideoReader
    from keyshape.tracker.labelling import dlib_landmarker as dl
    ref = np.load(shared_data / "video" / "references" / "glasses_rom_references.npz")["dlib68"].astype(float)
    frames = [40, 120, 200, 420]
    imgs = VideoReader(shared_data / "video" / "glasses_rom.mp4", gray=True).read_frames(frames)
    h, w = imgs[0].shape
    z = 1.8
    x0, y0 = np.clip(np.median(ref.reshape(-1, 2), 0) - (w / z / 2, h / z / 2), 0, (w - w / z, h - h / z))
    A = np.array([[z, 0, -z * x0], [0, z, -z * y0]])

    def errors():
        out = []
        for i, g in zip(frames, imgs):
            pts = landmarker.detect(cv2.warpAffine(g, A, (w, h), flags=cv2.INTER_LINEAR), averaged=True)
            want = ref[i] * z - (z * x0, z * y0)
            out.append(np.linalg.norm(pts - want, axis=1).mean() / np.linalg.norm(want[36] - want[45]))
        return np.array(out)

    assert errors().max() < 0.015
    monkeypatch.setattr(dl, "inside", lambda box, shape: True)        # never bordered
    assert errors()[1] > 0.04


def test_a_close_up_the_detector_misses_is_read_near_the_whole_video_pass(landmarker, shared_data):
    """Frame 541 of the same close-up: dlib's detector finds no face, bordered or not. The pre-fill then reads it
    from a box around the whole-video pass's points of that frame (here: the reference points of the frame
    before, as the pass carries them), within 0.02 inter-ocular distances of the frame's own reference points;
    without them it gives nothing (the label page's generic shape)."""
    import cv2

    from keyshape.base.formats.video import VideoReader
    from keyshape.base.schemes import load_scheme
    from keyshape.tracker.labelling.prepare import prefill
    ref = np.load(shared_data / "video" / "references" / "glasses_rom_references.npz")["dlib68"].astype(float)
    img = VideoReader(shared_data / "video" / "glasses_rom.mp4").read_frames([541])[0]
    h, w = img.shape[:2]
    z = 1.8
    x0, y0 = np.clip(np.median(ref.reshape(-1, 2), 0) - (w / z / 2, h / z / 2), 0, (w - w / z, h - h / z))
    A = np.array([[z, 0, -z * x0], [0, z, -z * y0]])
    close = cv2.warpAffine(img, A, (w, h), flags=cv2.INTER_LINEAR)
    want, near = (ref[k] * z - (z * x0, z * y0) for k in (541, 540))
    assert landmarker.detect(close) is None
    pts = landmarker.read_around(close, near, averaged=True)
    assert np.linalg.norm(pts - want, axis=1).mean() / np.linalg.norm(want[36] - want[45]) < 0.02
    scheme = load_scheme("contours48").full()
    assert prefill(close[None], scheme, landmarker)[0] is None
    got = prefill(close[None], scheme, landmarker, near[None])[0]
    assert got is not None and got.shape == (scheme.n_points, 2)
