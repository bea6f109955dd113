import numpy as np

from keyshape.base.draw import contact_sheet, crop_around, draw_shape
from keyshape.base.schemes import load_scheme


def test_draw_marks_pixels_on_contours_only():
    s = load_scheme("contours48")
    img = np.zeros((200, 200), np.uint8)
    pts = np.full((48, 2), np.nan)
    pts[28:40] = np.c_[50 + 100 * np.linspace(0, 1, 12), np.full(12, 100.0)]
    out = draw_shape(img, pts, s)
    assert out.shape == (200, 200, 3)
    ys, xs = np.nonzero(out.sum(axis=2))
    assert abs(ys.mean() - 100) < 2 and xs.min() >= 45 and xs.max() <= 155


def test_contact_sheet_and_crop():
    ims = [np.full((100, 200, 3), i * 40, np.uint8) for i in range(5)]
    sheet = contact_sheet(ims, [f"#{i}" for i in range(5)], columns=3, tile_width=100, pad=4)
    assert sheet.shape == (2 * (50 + 4) + 4, 3 * (100 + 4) + 4, 3)
    crop, p = crop_around(np.zeros((300, 300)), np.array([[100.0, 100], [150, 120]]), margin=0.0)
    assert crop.shape == (50, 50) and np.allclose(p.min(axis=0), [0, 15])
