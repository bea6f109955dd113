"""The preview's rig renderer (retarget/output/preview.py): culling what no frame shows, the float32
deformation of the moving shapes and the encoding thread leave the picture as it was.

The rig: the shipped ICT-FaceKit face skin (9,409 vertices, 18,461 triangles; the nose, lids and
lips hide parts of it), a few shapes, with head turns, at 160 px.
"""
from __future__ import annotations

import numpy as np
import pytest
from keyshape.retarget.rig.model import Rig

from keyshape.base.formats.obj import Mesh

SHAPES = ("jawOpen", "mouthSmile_L", "mouthFunnel", "eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "noseSneer_R")


@pytest.fixture(scope="module")
def face():
    from keyshape.retarget.targets.demo import load_expressions
    ex = load_expressions()
    pick = [ex.names.index(n) for n in SHAPES]
    rig = Rig(list(SHAPES), ex.neutral, ex.deltas[pick], Mesh(ex.neutral, list(ex.triangles)))
    rng = np.random.default_rng(5)
    curves = rng.uniform(0, 1, (30, len(SHAPES))) * (rng.uniform(size=(30, len(SHAPES))) < 0.5)
    from keyshape.retarget.output.preview import head_rotations
    turns = head_rotations(["headYaw", "headPitch"], rng.uniform(-25, 25, (30, 2)))
    return rig, curves, turns


def differ(a: np.ndarray, b: np.ndarray) -> float:
    """Share of pixels whose colour differs by more than 30 of 255 levels in a channel."""
    return float((np.abs(a.astype(int) - b.astype(int)).max(axis=2) > 30).mean())


def zbuffer_reference(r, v: np.ndarray) -> np.ndarray:
    """The exact picture of ``r``'s fitted triangles at ``v`` (n_vertices, 3): each pixel coloured as
    ``r`` colours the triangle a z-buffer finds nearest there (layers as the painter's order)."""
    from keyshape.base.raster import rasterize
    tri, mat = r.tri_all_, r.mat_all_
    v = np.asarray(v, np.float32)
    fn = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    vn = np.stack([np.bincount(tri.ravel(), np.repeat(fn[:, d], 3), minlength=len(v)) for d in range(3)], 1)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
    n = vn[tri].sum(axis=1)
    lam = np.clip(n @ r.l_ / np.linalg.norm(n, axis=1), 0, 1) * (1 - r.ambient) + r.ambient
    level = np.minimum((lam * r.levels).astype(int), r.levels - 1)
    colour = np.array(r.colours_)[mat * r.levels + level]
    p = r.camera_.project(v)[tri]
    lift = (np.ptp(p[..., 2]) + 1) * r.layer_[mat]
    w, h = r.size
    f = rasterize(p[..., :2].reshape(-1, 2), (-p[..., 2] - lift[:, None]).ravel(),
                  np.arange(3 * len(tri)).reshape(-1, 3), w, h)
    img = np.empty((h * w, 3), np.uint8)
    img[:] = r.background
    img[f.pixel] = np.round(colour[f.triangle])
    return img.reshape(h, w, 3)


def test_culling_hidden_triangles_leaves_the_picture_as_it_was(face):
    from keyshape.retarget.output.preview import RigRenderer
    rig, curves, turns = face
    fitted = slice(0, 20)                    # fitted on 20 frames, checked on those and 10 more it never saw
    full = RigRenderer(rig, (160, 160)).fit(curves[fitted], turns[fitted])
    cull = RigRenderer(rig, (160, 160), cull_hidden=True).fit(curves[fitted], turns[fitted])
    assert len(cull.tri_fit_) < 0.97 * len(full.tri_fit_)            # the inside of the nostrils, the lids' folds
    worst = max(differ(full.render_curves(c, R), cull.render_curves(c, R)) for c, R in zip(curves, turns))
    assert worst < 0.003
    # against the exact (z-buffer) picture: the painter's edges and bands cost 1.3-1.9% of the pixels at
    # 160 px (about 0.5% on the whole ICT-FaceKit head at 480 px); culling adds nothing to that
    full.tri_all_, full.mat_all_ = full.tri_fit_, full.mat_fit_
    for c, R in zip(curves[::7], turns[::7]):
        v = full.pose(rig.evaluate(c[None]), R[None])[0]
        ref = zbuffer_reference(full, v)
        assert differ(ref, full.render(v)) < 0.025
        assert differ(ref, cull.render(v)) < differ(ref, full.render(v)) + 0.002


def test_float32_deformation_of_the_moving_shapes_matches_the_rig(face):
    from keyshape.retarget.output.preview import RigRenderer
    rig, curves, _ = face
    c = curves[:6].copy()
    c[:, 2] = 0.0                                    # a shape that does not move in the fitted curves
    r = RigRenderer(rig, (160, 160)).fit(c)
    assert 2 not in r.moving_
    for row in (c[3], curves[7]):                    # the float32 product; a shape outside it (float64 path)
        assert differ(r.render_curves(row), r.render(rig.evaluate(row[None])[0])) < 0.001


def test_the_encoding_thread_writes_every_frame_in_order_and_reports_failure(tmp_path):
    import cv2
    from keyshape.retarget.output.preview_cli import _maybe_writer
    out = tmp_path / "v.avi"
    with _maybe_writer(out, 10.0) as write:
        for k in range(12):
            write(np.full((32, 48, 3), 20 * k, np.uint8))
    cap = cv2.VideoCapture(str(out))
    means = []
    while (frame := cap.read())[0]:
        means.append(frame[1].mean())
    assert len(means) == 12 and np.all(np.diff(means) > 10)
    (tmp_path / "f").write_text("a file, not a folder")
    with pytest.raises(OSError), _maybe_writer(tmp_path / "f" / "v.avi", 10.0) as write:
        for _ in range(30):
            write(np.zeros((32, 48, 3), np.uint8))
    assert not list(tmp_path.glob("f*/*.avi"))
