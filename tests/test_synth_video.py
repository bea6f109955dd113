"""Synthetic camcorder footage: outputs, determinism, ground truth on the rendered features, label choice, errors."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from keyshape.data_synth.face_model import COMPONENTS, FaceModel
from keyshape.data_synth.video import SyntheticVideo, parse_size, select_label_frames, synthesize
from keyshape.cli import main
from keyshape.base.errors import InputError
from keyshape.base.formats.tracks import read_tracks
from keyshape.base.formats.labels import read_labels
from keyshape.base.schemes import load_scheme
from keyshape.base.formats.video import VideoReader, video_info

SCHEME = load_scheme("contours48")


@pytest.fixture(scope="module")
def sv() -> SyntheticVideo:
    return SyntheticVideo(frames=150, seed=0)


def _open_eye_frames(sv: SyntheticVideo, n: int = 4) -> list[int]:
    """Frames where both pupils lie wholly inside the eye opening (no lid over them)."""
    c, m = sv.curves, sv.model
    ok = np.ones(sv.n_frames, bool)
    for k, name in enumerate(("left", "right")):
        up, lo = c[f"eye_{name}_upper"], c[f"eye_{name}_lower"]
        ic = c["iris"][:, k]
        for dx in (-m.pupil_radius, 0.0, m.pupil_radius):
            x = ic[:, 0] + dx
            yu = np.array([np.interp(xi, u[:, 0], u[:, 1]) for xi, u in zip(x, up)])
            yl = np.array([np.interp(xi, lo_[:, 0], lo_[:, 1]) for xi, lo_ in zip(x, lo)])
            ok &= (yu < ic[:, 1] - m.pupil_radius - 1.5) & (yl > ic[:, 1] + m.pupil_radius + 1.5)
    idx = np.flatnonzero(ok)
    assert len(idx) >= n, "performance has too few open-eye frames"
    return idx[np.linspace(0, len(idx) - 1, n).round().astype(int)].tolist()


def _profile(channel: np.ndarray, p: np.ndarray, d: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``channel`` at ``p + s * d`` (pixel-centre coordinates)."""
    q = p[None, :] + s[:, None] * d[None, :]
    return map_coordinates(channel, [q[:, 1], q[:, 0]], order=1, mode="nearest")


# --------------------------------------------------------------------------- outputs

def test_synthesize_writes_every_output(tmp_path):
    out = synthesize(tmp_path / "f", frames=24, seed=1, size=(320, 240), fps=25.0, labels=6,
                     preview=tmp_path / "sheet.png")
    assert set(out) == {"video", "truth", "labels", "truth_json", "preview"}
    info = video_info(out["video"])
    assert (info.width, info.height) == (320, 240) and info.fps == pytest.approx(25.0)
    assert sum(1 for _ in VideoReader(out["video"])) == 24
    tr = read_tracks(out["truth"])
    assert tr.n_frames == 24 and tr.n_points == SCHEME.n_points
    assert np.all(tr.confidence == 1) and np.all(tr.success)
    np.testing.assert_allclose(tr.time, np.arange(24) / 25.0, atol=1e-6)
    truth = json.loads(out["truth_json"].read_text())
    assert truth["components"] == list(COMPONENTS)
    w = np.array(truth["weights"])
    assert w.shape == (24, len(COMPONENTS)) and w.min() >= 0 and w.max() <= 1
    neutral, basis = np.array(truth["neutral"]), np.array(truth["basis"])
    assert neutral.shape == (48, 2) and basis.shape == (len(COMPONENTS), 48, 2)
    assert truth["seed"] == 1 and truth["size"] == [320, 240] and truth["fps"] == 25.0
    # the CSV pose maps the model-frame truth onto the image-frame truth
    model = np.array(truth["model_points"])
    img = np.einsum("nij,npj->npi", tr.pose[:, :, :2], model) + tr.pose[:, None, :, 2]
    np.testing.assert_allclose(img, tr.points, atol=2e-3)
    frames, shapes = read_labels(out["labels"], n_points=48)
    assert len(frames) == 6 and len(set(frames.tolist())) == 6
    np.testing.assert_allclose(shapes, tr.points[frames], atol=1e-3)
    sheet = cv2.imread(str(out["preview"]))
    assert sheet is not None and sheet.shape[0] > 100 and sheet.shape[1] > 300


def test_synthesis_is_deterministic_for_a_seed(tmp_path):
    a, b = SyntheticVideo(frames=40, seed=7, size=(320, 240)), SyntheticVideo(frames=40, seed=7, size=(320, 240))
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.weights, b.weights)
    for t in (0, 17, 39):
        assert np.array_equal(a.frame(t), b.frame(t))
    assert np.array_equal(a.frame(17), a.frame(17))          # a frame depends only on (seed, index)
    c = SyntheticVideo(frames=40, seed=8, size=(320, 240))
    assert not np.allclose(a.points, c.points)
    assert np.abs(a.frame(17).astype(int) - c.frame(17).astype(int)).mean() > 5
    o1 = synthesize(tmp_path / "a", frames=8, seed=7, size=(160, 120), labels=2)
    o2 = synthesize(tmp_path / "b", frames=8, seed=7, size=(160, 120), labels=2)
    for key in ("truth", "truth_json"):
        assert o1[key].read_bytes() == o2[key].read_bytes()


# --------------------------------------------------------------------------- ground truth on the features

def pupil_errors(image: np.ndarray, points: np.ndarray, radius: float = 3.5) -> list[float]:
    """Distance from each true pupil to the darkest pupil-sized blob inside its true eye contour.

    The blob is the minimum of the image averaged over a disc of ``radius``
    pixels (robust to noise and compression blocks), refined to sub-pixel by a
    parabola through its neighbours in x and in y.
    """
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float64)
    k = int(np.ceil(radius))
    yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
    disc = (xx ** 2 + yy ** 2 <= radius ** 2).astype(np.float64)
    dark = cv2.filter2D(gray, -1, disc / disc.sum(), borderType=cv2.BORDER_REPLICATE)
    errs = []
    for eye, pupil in (("eye_left", 26), ("eye_right", 27)):
        mask = np.zeros(gray.shape, np.uint8)
        poly = points[list(SCHEME.contours[eye])]
        cv2.fillPoly(mask, [np.round(poly * 16).astype(np.int32)], 1, cv2.LINE_8, 4)
        y, x = np.unravel_index(np.argmin(np.where(mask > 0, dark, np.inf)), gray.shape)
        sub = []
        for lo, mid, hi in ((dark[y, x - 1], dark[y, x], dark[y, x + 1]), (dark[y - 1, x], dark[y, x], dark[y + 1, x])):
            den = lo - 2 * mid + hi
            sub.append(0.5 * (lo - hi) / den if den > 0 else 0.0)
        errs.append(float(np.linalg.norm([x + sub[0] - points[pupil, 0], y + sub[1] - points[pupil, 1]])))
    return errs


def lip_corner_errors(image: np.ndarray, points: np.ndarray) -> list[float]:
    """Distance along the mouth axis from each true outer lip corner to the lip/skin colour boundary.

    The boundary is where the redness crosses half-way between the lip and the
    skin. At a tapering corner this estimate sits inside the true tip (the
    pixels at the tip are mostly skin): about 0.4-0.6 px on the sharp canvas,
    about 1 px after the camera blur, so tolerances allow for it.
    """
    img = cv2.GaussianBlur(image.astype(np.float64), (3, 3), 0)
    b, g, r = img[..., 0], img[..., 1], img[..., 2]
    chroma = (r - g) / (r + g + b + 1.0)          # lips are redder than skin; shading cancels
    centre = points[28:40].mean(axis=0)
    errs = []
    for corner in (28, 34):
        d = points[corner] - centre
        d /= np.linalg.norm(d)
        s = np.arange(-4.0, 10.0, 0.05)
        prof = _profile(chroma, points[corner], d, s)
        lip = prof[s < 0].max()                          # the lip (or the mouth inside), however thin
        skin = prof[(s > 7) & (s < 9)].mean()
        assert lip > skin + 0.05, (corner, lip, skin)
        thr = 0.5 * (lip + skin)
        k = np.flatnonzero(prof > thr).max()             # last lip-coloured sample going outwards
        errs.append(abs(s[k] + (prof[k] - thr) / (prof[k] - prof[k + 1]) * 0.05))
    return errs


def test_pupils_are_the_darkest_blob_in_each_eye(sv):
    errs = [e for t in _open_eye_frames(sv) for e in pupil_errors(sv.frame(t), sv.points[t])]
    assert max(errs) < 1.5, errs


def test_lip_corners_are_on_the_lip_colour_boundary(sv):
    frames = np.linspace(5, sv.n_frames - 5, 6).round().astype(int)
    errs = [e for t in frames for e in lip_corner_errors(sv.frame(t), sv.points[t])]
    assert max(errs) < 1.5, errs


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_truth_on_features_after_encoding(tmp_path, seed):
    """Other seeds (other faces and looks): pupils on the decoded mp4v video, lip corners before encoding
    (mp4v halves the colour resolution, which moves colour boundaries by about a pixel)."""
    out = synthesize(tmp_path / "f", frames=120, seed=seed, labels=2)
    sv = SyntheticVideo(frames=120, seed=seed)
    frames = dict(VideoReader(out["video"]))
    pupil = [e for t in _open_eye_frames(sv, 8) for e in pupil_errors(frames[t], sv.points[t])]
    lips = [e for t in range(0, 120, 10) for e in lip_corner_errors(sv.frame(t), sv.points[t])]
    assert max(pupil) < 1.5 and np.mean(pupil) < 0.5, pupil
    assert max(lips) < 2.0 and np.median(lips) < 1.3, lips


def test_eye_contours_lie_on_the_lid_edges(sv):
    """The upper-lid points sit on the step from the dark lash line to the eye (steepest descent outwards)."""
    errs = []
    for t in _open_eye_frames(sv):
        gray = cv2.cvtColor(sv.frame(t), cv2.COLOR_BGR2GRAY).astype(np.float64)
        pts = sv.points[t]
        for a, p, b in ((10, 11, 12), (12, 13, 14), (18, 19, 20), (20, 21, 22)):   # beside the iris
            tang = pts[b] - pts[a]
            out = np.array([tang[1], -tang[0]]) / np.linalg.norm(tang)     # normal pointing out of the eye (up)
            assert out[1] < 0
            s = np.arange(-1.5, 1.5, 0.05)       # a GT off by more than 1 px puts the steepest step >1 px away
            prof = _profile(gray, pts[p], out, s)
            if np.ptp(prof) < 60:              # the iris under the lid: too little contrast to locate
                continue
            errs.append(s[np.argmin(np.gradient(prof))])
    assert len(errs) >= 12
    assert np.median(np.abs(errs)) < 0.6 and np.max(np.abs(errs)) < 1.0, errs


def _dist_to_polyline(q: np.ndarray, line: np.ndarray) -> np.ndarray:
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.clip(np.einsum("qsd,sd->qs", q[:, None] - a[None], ab) / np.einsum("sd,sd->s", ab, ab), 0, 1)
    return np.linalg.norm(q[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1).min(axis=1)


@pytest.mark.parametrize("contour, curve, start", [("lip_outer", "lip_outer", 28), ("lip_inner", "lip_inner", 40),
                                                   ("eye_left", "eye_left", 10), ("eye_right", "eye_right", 18)])
def test_contours_run_on_the_curves_evenly_spaced(sv, contour, curve, start):
    t = int(np.argmax(sv.weights[:, 0]))                      # widest mouth: most curved contours
    n = len(SCHEME.contours[contour])
    pts = sv.model_points[t, start:start + n]
    up, lo = sv.curves[f"{curve}_upper"][t], sv.curves[f"{curve}_lower"][t]
    half = n // 2
    upper_pts, lower_pts = pts[:half + 1], np.vstack([pts[half:], pts[:1]])
    assert _dist_to_polyline(upper_pts, up).max() < 1e-6 and _dist_to_polyline(lower_pts, lo).max() < 1e-6
    # image-left corner first, upper curve first (smaller y), corners are the curves' ends
    np.testing.assert_allclose(pts[0], up[0], atol=1e-6)
    np.testing.assert_allclose(pts[half], up[-1], atol=1e-6)
    assert pts[0, 0] < pts[half, 0] and pts[half // 2, 1] <= pts[half + half // 2, 1]
    for chain, line in ((upper_pts, up), (lower_pts, lo)):
        chords = np.linalg.norm(np.diff(chain, axis=0), axis=1)
        if np.linalg.norm(np.diff(line, axis=0), axis=1).sum() > 5:
            np.testing.assert_allclose(chords, chords.mean(), rtol=0.05)


def test_side_convention_of_component_names():
    m = FaceModel(0)
    k = {n: i for i, n in enumerate(COMPONENTS)}
    w = np.zeros((1, len(COMPONENTS)))
    w[0, k["eyeBlink_L"]] = 1.0
    p = m.landmarks(w)[0]
    opening = lambda q, e: q[[e + 5, e + 6, e + 7], 1].mean() - q[[e + 1, e + 2, e + 3], 1].mean()  # noqa: E731
    assert opening(p, 18) < 1.5 and opening(p, 10) > 10   # eyeBlink_L closes the image-right eye
    w[:] = 0
    w[0, k["mouthSmile_L"]] = 1.0
    p0, p1 = m.landmarks(np.zeros_like(w))[0], m.landmarks(w)[0]
    assert p1[34, 1] < p0[34, 1] - 3 and abs(p1[28, 1] - p0[28, 1]) < 0.5   # image-right corner rises


# --------------------------------------------------------------------------- labels

def test_label_frames_are_distinct_and_span_the_weights():
    sv = SyntheticVideo(frames=300, seed=2, size=(160, 120))
    idx = sv.label_frames(12)
    assert len(set(idx.tolist())) == 12 and np.all(np.diff(idx) > 0)
    w = sv.weights
    for j, name in enumerate(COMPONENTS):
        if w[:, j].max() > 0.3:
            assert w[idx, j].max() >= 0.6 * w[:, j].max(), name
    f = w[idx]
    d = np.linalg.norm(f[:, None] - f[None], axis=-1) + np.eye(12) * 99
    assert d.min() > 0.25                # no near-duplicates: any two labels differ by a quarter weight or more


def test_select_label_frames_picks_extremes_first():
    f = np.zeros((50, len(COMPONENTS)))
    f[10, 0] = 1.0
    f[30, 3] = 0.8
    f[31, 3] = 0.79
    assert select_label_frames(f, 3).tolist() == [0, 10, 30]


# --------------------------------------------------------------------------- errors

@pytest.mark.parametrize("kwargs, match", [
    ({"frames": 0}, "frames"),
    ({"frames": -5}, "frames"),
    ({"frames": 10, "labels": 11}, "labels"),
    ({"labels": 0}, "labels"),
    ({"size": (20, 20)}, "size"),
    ({"fps": 0}, "fps"),
    ({"seed": -1}, "seed"),
], ids=["zero-frames", "negative-frames", "labels>frames", "zero-labels", "tiny-size", "zero-fps", "neg-seed"])
def test_bad_arguments_raise_input_error(tmp_path, kwargs, match):
    with pytest.raises(InputError, match=match):
        synthesize(tmp_path / "x", **{"frames": 10, "labels": 2, **kwargs})
    assert not (tmp_path / "x" / "video.mp4").exists()


@pytest.mark.parametrize("text", ["640by480", "640x", "x480", "640x480x3", "abc"])
def test_bad_size_string(text):
    with pytest.raises(InputError, match="WIDTHxHEIGHT"):
        parse_size(text)
    assert parse_size("320x240") == (320, 240)


def test_cli_reports_bad_size_in_one_line(tmp_path, capsys):
    rc = main(["synth", "video", str(tmp_path / "o"), "--size", "640by480"])
    err = capsys.readouterr().err
    assert rc == 2 and "640by480" in err and err.count("\n") == 1


def test_cli_writes_outputs(tmp_path, capsys):
    rc = main(["synth", "video", str(tmp_path / "o"), "--frames", "6", "--size", "160x120", "--labels", "2",
               "--seed", "4"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "ms/frame" in out and "truth.csv" in out
    assert read_tracks(tmp_path / "o" / "truth.csv").n_frames == 6
