"""Gray frames from the decoder's luma plane (``VideoReader(gray=True, luma=True)``, what the tracker decodes):
the same gray levels as OpenCV's BGR decoding and ``cvtColor`` to the colour conversion's rounding, the BGR
route kept where a table cannot be told, and seeking frame-exact on it too."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from keyshape.base.formats.video import VideoReader, luma_table, video_writer


def _face_like(k: int, w: int = 160, h: int = 120) -> np.ndarray:
    """A skin-toned frame with soft shading, a dark moving blob and a saturated red patch (clipping)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    shade = 0.55 + 0.45 * np.cos((xx - w / 2) / w * 2.5) * np.cos((yy - h / 2) / h * 2.0)
    img = np.stack([110 * shade + 20, 140 * shade + 25, 200 * shade + 30], axis=-1)     # BGR skin
    blob = np.exp(-(((xx - 40 - k) ** 2 + (yy - 60) ** 2) / 120.0))
    img *= (1 - 0.8 * blob)[..., None]
    img[10:25, 120:150] = (20, 20, 230)
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("suffix", [".mp4", ".avi"], ids=["mp4v-video-range", "mjpg-full-range"])
def test_luma_frames_are_the_bgr_gray_to_the_conversion_rounding(tmp_path, suffix):
    video = tmp_path / f"clip{suffix}"
    with video_writer(video, 25.0, (160, 120)) as w:
        for k in range(20):
            w.write(_face_like(k))
    luma = VideoReader(video, gray=True, luma=True)
    assert luma.luma_table_ is not None                          # the fast route was taken
    table = luma.luma_table_.astype(float)
    slope = (table[200] - table[60]) / 140.0
    assert (1.10 <= slope <= 1.22) if suffix == ".mp4" else (0.97 <= slope <= 1.03)    # video range / full (JPEG)
    bgr = VideoReader(video, gray=True)
    n = 0
    for (i, a), (j, b) in zip(luma, bgr):
        assert i == j and a.shape == b.shape == (120, 160) and a.dtype == np.uint8
        d = cv2.absdiff(a, b)
        assert d.mean() <= 0.75 and np.percentile(d, 99.9) <= 3, (i, d.mean(), d.max())
        n += 1
    assert n == 20 and luma.n_read == 20 and not luma.truncated


def test_a_first_frame_without_contrast_keeps_the_bgr_route(tmp_path):
    video = tmp_path / "fade.mp4"
    with video_writer(video, 25.0, (160, 120)) as w:
        w.write(np.full((120, 160, 3), 16, np.uint8))                 # a fade from black: range cannot be told
        for k in range(5):
            w.write(_face_like(k))
    assert luma_table(video) is None
    luma, bgr = VideoReader(video, gray=True, luma=True), VideoReader(video, gray=True)
    assert luma.luma_table_ is None
    for (_, a), (_, b) in zip(luma, bgr):
        np.testing.assert_array_equal(a, b)


def test_luma_frames_from_a_start_equal_the_sequential_decode(tmp_path):
    video = tmp_path / "clip.mp4"
    with video_writer(video, 25.0, (160, 120)) as w:
        for k in range(60):                  # every frame different: a wrong index cannot match by chance
            w.write(_face_like(k))
    reader = VideoReader(video, gray=True, luma=True)
    assert reader.luma_table_ is not None
    every = [f for _, f in reader]
    for start in (1, 12, 13, 47):
        got = list(reader.frames(start, start + 4))
        assert [i for i, _ in got] == list(range(start, start + 4))
        for i, f in got:
            np.testing.assert_array_equal(f, every[i], err_msg=f"frame {i} read from {start}")
    np.testing.assert_array_equal(reader.read_frames([30, 2]), np.stack([every[30], every[2]]))


def test_the_gray_route_without_luma_is_unchanged(tmp_path):
    video = tmp_path / "clip.mp4"
    with video_writer(video, 25.0, (160, 120)) as w:
        for k in range(3):
            w.write(_face_like(k))
    plain = VideoReader(video, gray=True)
    assert plain.luma_table_ is None
    for (_, g), (_, c) in zip(plain, VideoReader(video)):
        np.testing.assert_array_equal(g, cv2.cvtColor(c, cv2.COLOR_BGR2GRAY))
