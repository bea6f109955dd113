"""iBUG-68 -> contours48 conversion: arc-length resampling, corners kept, pupils on the dark blob."""
from __future__ import annotations

import numpy as np
import pytest

from keyshape.base.errors import InputError
from keyshape.tracker.labelling.convert import find_pupil, ibug68_to_contours48, resample_curve
from keyshape.tracker.labelling.prepare import mean_ibug68
from keyshape.base.schemes import load_scheme


def test_resample_straight_line_is_even():
    out = resample_curve(np.array([[0.0, 0], [1, 0], [7, 0], [10, 0]]), 6)
    np.testing.assert_allclose(out, np.column_stack([np.linspace(0, 10, 6), np.zeros(6)]), atol=1e-9)


def test_resample_arc_even_by_arc_length_and_keeps_ends():
    t = np.array([0.0, 0.3, 0.9, 1.3, 1.9, 2.2, 2.8, np.pi])  # uneven samples of a half circle
    pts = np.column_stack([np.cos(t), np.sin(t)]) * 20
    out = resample_curve(pts, 7)
    np.testing.assert_allclose(out[[0, -1]], pts[[0, -1]])
    ang = np.arctan2(out[:, 1], out[:, 0])
    np.testing.assert_allclose(np.diff(ang), np.pi / 6, atol=0.02)  # even along the arc
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 20, atol=0.2)  # on the curve


def test_resample_errors():
    with pytest.raises(InputError, match="curve needs"):
        resample_curve(np.zeros((1, 2)), 5)


def face68():
    return mean_ibug68() * 100 + [200, 150]


def test_corners_and_layout():
    p = face68()
    q = ibug68_to_contours48(p)
    sch = load_scheme("contours48")
    assert q.shape == (48, 2)
    for c48, c68 in [(10, 36), (14, 39), (18, 42), (22, 45), (28, 48), (34, 54), (40, 60), (44, 64),
                     (0, 17), (4, 21), (5, 22), (9, 26)]:
        np.testing.assert_allclose(q[c48], p[c68], err_msg=f"contours48 {c48} vs ibug {c68}")
    np.testing.assert_allclose(sch.interocular_distance(q), np.linalg.norm(p[36] - p[45]))
    for name in ("eye_left", "eye_right", "lip_outer", "lip_inner"):
        idx = list(sch.contours[name])
        k = len(idx) // 2
        upper, lower = q[idx[1:k]], q[idx[k + 1:]][::-1]
        assert np.all(upper[:, 1] < lower[:, 1]), name  # upper curve above the lower one
        assert np.all(np.diff(upper[:, 0]) > 0), name  # runs image-left to image-right
    # pupils without an image: inside their eyes
    for e, pu in (("eye_left", 26), ("eye_right", 27)):
        ex = q[list(sch.contours[e])]
        assert ex[:, 0].min() < q[pu, 0] < ex[:, 0].max()


def test_upper_lid_points_evenly_spaced():
    q = ibug68_to_contours48(face68())
    lid = q[[10, 11, 12, 13, 14]]
    # evenly spaced by arc length: chords of a smooth curve nearly equal
    d = np.linalg.norm(np.diff(lid, axis=0), axis=1)
    assert d.max() / d.min() < 1.15


def test_pupil_found_on_dark_blob():
    import cv2
    img = np.full((120, 160), 200, np.uint8)
    eye = np.array([[40, 60], [60, 50], [80, 48], [100, 50], [120, 60], [100, 70], [80, 72], [60, 70]], float)
    cv2.circle(img, (92, 60), 9, 40, -1)  # iris off-centre, right of the eye's centroid
    img = cv2.GaussianBlur(img, (5, 5), 1.0)
    c = find_pupil(img, eye)
    assert np.linalg.norm(c - [92, 60]) < 1.5
    # uniform eye (closed / no contrast): falls back near the contour's centroid
    c2 = find_pupil(np.full((120, 160), 128, np.uint8), eye)
    assert np.linalg.norm(c2 - eye.mean(axis=0)) < 12


def test_bad_input_named():
    with pytest.raises(InputError, match=r"\(68, 2\)"):
        ibug68_to_contours48(np.zeros((48, 2)))
    p = face68()
    p[3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        ibug68_to_contours48(p)


def test_mid_lip_points_are_ibug_mid_points_under_a_head_turn():
    """The lips' middle points stay on the face's mid-lip feature (iBUG 51, 57, 62, 66) when the head
    turns: with plain arc-length spacing the nearer, longer-looking half of the lip pulls them sideways."""
    p = face68()
    mouth = np.arange(48, 68)
    x0 = p[48, 0]
    w = p[54, 0] - x0
    u = (p[mouth, 0] - x0) / w
    p[mouth, 0] = x0 + w * u ** 1.6          # yaw-like foreshortening: the image-left half looks shorter
    q = ibug68_to_contours48(p)
    for c48, c68 in ((31, 51), (37, 57), (42, 62), (46, 66)):
        np.testing.assert_allclose(q[c48], p[c68], atol=1e-9, err_msg=f"contours48 {c48} vs ibug {c68}")
    # the other lip points evenly spaced by arc length on each side of the middle point
    for half in ([28, 29, 30, 31], [31, 32, 33, 34], [34, 35, 36, 37], [37, 38, 39, 28]):
        d = np.linalg.norm(np.diff(q[half], axis=0), axis=1)
        assert d.max() / d.min() < 1.2, half
    # without the anchor, the middle point slides towards the longer-looking half (by 10% of the width)
    plain = resample_curve(p[[48, 49, 50, 51, 52, 53, 54]], 7)
    assert plain[3, 0] > p[51, 0] + 0.05 * w


def test_resample_anchor_keeps_the_anchor_in_the_middle():
    pts = np.array([[0.0, 0], [1, 0], [2, 0], [8, 0], [10, 0]])
    out = resample_curve(pts, 5, anchor=2)
    np.testing.assert_allclose(out, [[0, 0], [1, 0], [2, 0], [6, 0], [10, 0]], atol=1e-6)
