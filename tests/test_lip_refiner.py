"""The lips' shape fitted by analysis by synthesis after the eigen-points reading (issue 40 item 1):
:class:`keyshape.tracker.eigenpoints.ShapeRefiner` and :func:`keyshape.tracker.kernels.refine_shape`."""
from __future__ import annotations

import cv2
import numpy as np

from keyshape.base.schemes import load_scheme
from keyshape.tracker.eigenpoints import AppearanceModel, Pyramid, ShapeRefiner
from keyshape.tracker.kernels import refine_shape

SCHEME = load_scheme("contours48")
OUTER = list(SCHEME.contours["lip_outer"])
INNER = list(SCHEME.contours["lip_inner"])
H, W = 120, 160


def _mouth(gap: float, width: float = 56.0) -> np.ndarray:
    """contours48's 48 points with a mouth at (80, 60): outer lips on an ellipse, inner lips ``gap`` apart
    (corner, upper, corner, lower, as the scheme orders them); the other points at the origin."""
    pts = np.zeros((48, 2))
    a = np.linspace(np.pi, 0, 7)                           # image-left corner over the top to the right corner
    b = np.linspace(0, -np.pi, 7)[1:-1]                    # and back along the bottom
    t = np.concatenate([a, b])
    pts[OUTER] = np.column_stack([80 + width / 2 * np.cos(t), 60 - (6 + gap / 2) * np.sin(t)])
    ti = np.concatenate([np.linspace(np.pi, 0, 5), np.linspace(0, -np.pi, 5)[1:-1]])
    pts[INNER] = np.column_stack([80 + 0.4 * width * np.cos(ti), 60 - gap / 2 * np.sin(ti)])
    return pts


def _frame(pts: np.ndarray, rng) -> np.ndarray:
    """Skin with a smooth texture (the same in every frame), lips a darker grey, the mouth's inside darkest;
    ``rng`` adds a little pixel noise."""
    tex = cv2.GaussianBlur(np.random.default_rng(0).normal(size=(H, W)).astype(np.float32), (0, 0), 4.0)
    img = 150 + 200 * tex
    mask = np.zeros((H, W), np.uint8)
    cv2.fillPoly(mask, [np.round(pts[OUTER] * 8).astype(np.int32)], 1, shift=3)
    img[mask > 0] = 90 + 0.5 * (img[mask > 0] - 150)
    inner = np.zeros((H, W), np.uint8)
    cv2.fillPoly(inner, [np.round(pts[INNER] * 8).astype(np.int32)], 1, shift=3)
    img[inner > 0] = 25
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.8) + rng.normal(0, 2.0, (H, W))
    return np.clip(img, 0, 255).astype(np.uint8)


def test_the_lips_shape_fit_reads_an_opening_the_start_shrank():
    """Trained on four openings (2-14 px), the fit started at the training mean (8 px) finds a 12 px opening
    and a 4 px one within 0.5 px, and keeps the mouth's width: a linear reading's shrinkage toward the mean
    does not survive it."""
    rng = np.random.default_rng(0)
    gaps = [2.0, 6.0, 10.0, 14.0]
    shapes = np.stack([_mouth(g, w) for g, w in zip(gaps, (58.0, 62.0, 56.0, 60.0))])
    pose = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    pyrs = [Pyramid(_frame(s, np.random.default_rng(k))) for k, s in enumerate(shapes)]
    lr = ShapeRefiner.fit(sorted(OUTER + INNER), INNER, pyrs, [pose] * 4, shapes)
    start = shapes.mean(0)[lr.points]
    for gap in (12.0, 4.0):
        truth = _mouth(gap, 59.0)
        img = _frame(truth, rng)
        s = start.ravel().copy()
        crop, f, at = lr.image(Pyramid(img), pose, start)
        steps = refine_shape(crop, f, at, s, lr.tables(), lr.work(), 10)
        got = s.reshape(-1, 2)
        pts = dict(zip(lr.points.tolist(), got))
        read = pts[INNER[6]][1] - pts[INNER[2]][1]           # lower mid minus upper mid
        assert steps >= 1 and abs(read - gap) < 0.5, (gap, read)
        width = pts[OUTER[6]][0] - pts[OUTER[0]][0]
        assert abs(width - 59.0) < 1.0, width


def test_models_carry_the_lips_refiner_and_older_files_read_without_it(tmp_path):
    """``AppearanceModel(lip_refine=True)`` (the default) keeps a :class:`ShapeRefiner` for the lips,
    saved and loaded with the model; ``lip_refine=False`` and files written before it have none."""
    rng = np.random.default_rng(1)
    frames, labels = [], []
    for k, g in enumerate((2.0, 6.0, 10.0, 14.0, 8.0)):
        pts = _mouth(g, 56.0 + k)
        pts[:28] = np.column_stack([40 + 80 * rng.uniform(size=28), 15 + 25 * rng.uniform(size=28)])
        pts[10], pts[22] = (45, 30), (115, 30)
        frames.append(_frame(pts, np.random.default_rng(k)))
        labels.append(pts)
    model = AppearanceModel("contours48", n_morphs=4, rng=0).fit(frames, np.stack(labels))
    assert model.lip_refiner_ is not None and sorted(model.lip_refiner_.write) == sorted(OUTER + INNER)
    model.save(tmp_path / "m.npz")
    back = AppearanceModel.load(tmp_path / "m.npz")
    for k in ShapeRefiner.ARRAYS:
        np.testing.assert_array_equal(getattr(back.lip_refiner_, k), getattr(model.lip_refiner_, k))
    off = AppearanceModel("contours48", n_morphs=4, rng=0, lip_refine=False).fit(frames, np.stack(labels))
    assert off.lip_refiner_ is None
    mf = model.to_file()
    del mf.params["lip_refine"]
    for k in ShapeRefiner.ARRAYS:
        del mf.arrays[f"lip_refiner_{k}"]
    assert AppearanceModel.from_file(mf).lip_refiner_ is None


def test_the_compiled_fit_matches_its_parts():
    """The tracker's lips fit (:func:`~keyshape.tracker.kernels.lip_box` then
    :func:`~keyshape.tracker.kernels.refine_write`, one compiled call each) gives the points of
    :meth:`ShapeRefiner.image` and :func:`refine_shape` mapped back to the image, to rounding; and the
    samples' gradients from the 3 x 3 pixels they share are the differences of bilinear samples, border included."""
    from keyshape.tracker.kernels import PAD, _bilinear_grad, lip_box, padded, refine_write

    rng = np.random.default_rng(2)
    gaps = [2.0, 6.0, 10.0, 14.0]
    shapes = np.stack([_mouth(g, w) for g, w in zip(gaps, (58.0, 62.0, 56.0, 60.0))])
    pose = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    lr = ShapeRefiner.fit(sorted(OUTER + INNER), INNER, [Pyramid(_frame(s, np.random.default_rng(k)))
                                                         for k, s in enumerate(shapes)], [pose] * 4, shapes)
    img_pose = np.array([[1.1, 0.05, 3.0], [-0.04, 1.05, -2.0]])         # image_from_model
    truth = _mouth(11.0, 59.0)
    pyr = Pyramid(_frame(truth, rng))
    start = shapes.mean(0)
    points = start @ img_pose[:, :2].T + img_pose[:, 2]
    crop, f, at = lr.image(pyr, img_pose, start[lr.points])
    s = start[lr.points].ravel().copy()
    refine_shape(crop, f, at, s, lr.tables(), lr.work(), 6)
    want = s.reshape(-1, 2)[np.searchsorted(lr.points, lr.write)] @ img_pose[:, :2].T + img_pose[:, 2]
    s2, box = np.empty(2 * len(lr.points)), np.empty(4, np.intp)
    assert lip_box(img_pose, points, lr.points, f, pyr._sizes[0], s2, box)
    got = points.copy()
    refine_write(lr.crop(pyr, 0, box), f, img_pose, box, s2, lr.tables(), lr.work(), 6,
                 (np.searchsorted(lr.points, lr.write), lr.write), got)
    assert np.abs(got[lr.write] - want).max() < 1e-9
    others = np.setdiff1d(np.arange(len(points)), lr.write)
    assert np.array_equal(got[others], points[others])
    flat = crop[0, PAD:-PAD, PAD:-PAD].astype(np.float32)
    hh, ww = flat.shape

    def bilinear(x, y):                              # the border replicated
        x, y = min(max(x, 0.0), ww - 1.0), min(max(y, 0.0), hh - 1.0)
        ix, iy = min(int(x), ww - 2), min(int(y), hh - 2)
        ax, ay = x - ix, y - iy
        p = flat[iy:iy + 2, ix:ix + 2].astype(np.float64)
        v0, v1 = p[0, 0] + ax * (p[0, 1] - p[0, 0]), p[1, 0] + ax * (p[1, 1] - p[1, 0])
        return v0 + ay * (v1 - v0)

    img = padded(flat)
    for x, y in zip(rng.uniform(-4, ww + 3, 3000), rng.uniform(-4, hh + 3, 3000)):
        ref = (bilinear(x, y), bilinear(x + 0.5, y) - bilinear(x - 0.5, y), bilinear(x, y + 0.5) - bilinear(x, y - 0.5))
        assert np.allclose(_bilinear_grad(img, x + PAD, y + PAD), ref, rtol=0, atol=1e-9), (x, y)


def test_the_crop_is_blurred_as_gaussian_blur_blurs_it_in_float32():
    """:meth:`ShapeRefiner.crop` blurs the uint8 crop into float32 in one call (``cv2.sepFilter2D`` with
    ``_GAUSS``): the values of ``cv2.GaussianBlur`` of the crop converted to float32 first (to float32's
    rounding), within the replicated border :func:`~keyshape.tracker.kernels.padded` adds."""
    from keyshape.tracker.kernels import PAD

    frame = _frame(_mouth(8.0), np.random.default_rng(3))
    box = np.array([30, 20, 131, 97], np.intp)
    got = ShapeRefiner.crop(Pyramid(frame), 0, box)
    want = cv2.GaussianBlur(frame[20:97, 30:131].astype(np.float32), (0, 0), ShapeRefiner.BLUR,
                            borderType=cv2.BORDER_REPLICATE)
    assert got.dtype == np.float64 and got.shape == (3, 77 + 2 * PAD, 101 + 2 * PAD)
    img = got[0]
    assert np.abs(img[PAD:-PAD, PAD:-PAD] - want).max() < 1e-4
    assert np.array_equal(img[:PAD], np.repeat(img[PAD:PAD + 1], PAD, 0))
    assert np.array_equal(img[:, -PAD:], np.repeat(img[:, -PAD - 1:-PAD], PAD, 1))
    # the differences to the next column and row that the samples' gradients are read from
    assert np.array_equal(got[1][:, :-1], np.diff(img, axis=1)) and not got[1][:, -1].any()
    assert np.array_equal(got[2][:-1], np.diff(img, axis=0)) and not got[2][-1].any()
