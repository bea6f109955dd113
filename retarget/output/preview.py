"""Preview a take on a rig: the footage with its tracked contours beside the shaded character.

Design notes and figures: docs/retarget.md, "Notes on the code", ``retarget/output/preview.py``.
"""
from __future__ import annotations

import os
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from keyshape.base.errors import InputError
from keyshape.retarget.output.render import OrthoCamera
from keyshape.retarget.rig.model import Rig, material_parts


#: Drawing layers by material-name keyword (painter's order: lower first), so that the inner parts
#: (mouth, teeth, eyeballs) are covered by the skin around their opening whatever the depth bands, and
#: the iris is drawn over the sclera (ICT-FaceKit's iris lies inside the eyeball's shell, under the
#: cornea, which a depth test would let hide it); unknown materials are skin (layer 4), sorted by depth with it.
LAYERS = (("gum", 0), ("tongue", 0), ("socket", 0), ("teeth", 1), ("sclera", 2), ("iris", 3))


def layer_of(material: str) -> int:
    low = material.lower()
    return next((rank for key, rank in LAYERS if key in low), 4)


class RigRenderer:
    """Render frames of a rig (orthographic front view, mesh y up -> image y down).

    Parameters
    ----------
    rig : Rig with a mesh (faces)
    size : (width, height) of the rendered image
    light : direction towards the light
    ambient : ambient term
    levels : shade quantisation levels (per material)
    band : triangles per depth band (OpenCV fills a few hundred polygons per call faster than
        tens of thousands)
    background : BGR
    vertices : optional vertex subset to frame the camera on (default: the face skin for an
        ICT-FaceKit rig, else all vertices)
    landmarks : optional ``(W, scheme)``: the (n_points, n_vertices) matrix taking the rig's vertices
        to a landmark scheme's points (:func:`~keyshape.retarget.rig.model.rig_landmarks`) and the scheme;
        its contours (lids, brows, lips) are drawn over the shaded rig, in the colours of the actor's
        contours, so lids and brows read at a glance and compare with the actor's
    cull_hidden : drop, in :meth:`fit`, the triangles that no sampled frame of the curves shows
        (:meth:`visible_triangles`: the backs of the eyeballs, teeth behind closed lips, the inside of
        the mouth and nostrils), for rendering a take whose curves are known when fitting (a preview);
        off for rendering any mix of shapes (the pose editor's sliders)

    Attributes
    ----------
    camera_ : OrthoCamera (after :meth:`fit`)
    tri_fit_, mat_fit_ : the triangles drawn (rig vertex indices) and their material
    moving_ : the shapes that move in the fitted curves; their deltas at the vertices drawn
        (float32) make each frame's deformation one matrix product (:meth:`render_curves`)
    """

    def __init__(self, rig: Rig, size=(480, 480), light=(0.3, 0.4, 1.0), ambient: float = 0.18, levels: int = 24,
                 band: int = 2000, background=(40, 40, 40), vertices: np.ndarray | None = None,
                 landmarks: tuple[np.ndarray, Any] | None = None, cull_hidden: bool = False):
        if rig.mesh is None or not rig.mesh.polygons:
            raise InputError("the rig's neutral has no faces to render", rig.neutral_file)
        self.rig, self.size, self.light, self.ambient = rig, size, light, ambient
        self.levels, self.band, self.background, self.vertices = levels, band, background, vertices
        self.landmarks, self.cull_hidden = landmarks, cull_hidden
        tri = rig.mesh.triangles
        parts = [p for p in material_parts(rig.mesh) if p[2][3] > 0 and "lash" not in p[0].lower()]
        self.tri_ = np.concatenate([tri[p[1]] for p in parts])
        self.mat_ = np.concatenate([np.full(len(p[1]), i) for i, p in enumerate(parts)])
        self.layer_ = np.array([layer_of(p[0]) for p in parts])
        self.rgb_ = np.array([p[2][:3] for p in parts])[:, ::-1] * 255.0        # BGR
        li = np.asarray(light, float)
        self.l_ = li / np.linalg.norm(li)

    def fit(self, curves: np.ndarray | None = None, rotations: np.ndarray | None = None) -> "RigRenderer":
        """Choose one camera framing the rig over the given curves (a sample of frames).

        ``rotations`` (n, 3, 3): head rotations the frames will be rendered with (:meth:`pose`); the
        triangles that any of the extreme ones turns towards the camera are kept for drawing. When
        there is one per row of ``curves`` (row i's turn), ``cull_hidden`` samples the frames turned.
        """
        from keyshape.retarget.rig.model import ICT_FACE_SKIN, ICT_N_VERTICES
        vsel = self.vertices
        if vsel is None and self.rig.n_vertices == ICT_N_VERTICES:
            vsel = np.arange(ICT_FACE_SKIN)
        c = np.zeros((1, self.rig.n_shapes)) if curves is None else np.asarray(curves)[:: max(1, len(curves) // 20)]
        if self.landmarks is not None:            # framed on the face, as the actor's panel (face_crop)
            lm = np.einsum("pv,nvd->npd", self.landmarks[0], self.rig.evaluate(c), optimize=True)[..., :2]
            centre, side = face_square(lm.min(axis=(0, 1)), lm.max(axis=(0, 1)), down=-1.0)
            self.camera_ = OrthoCamera.fit(np.array([[*(centre - side / 2), 0.0], [*(centre + side / 2), 0.0]]),
                                           *self.size, margin=0.0)
        else:
            self.camera_ = OrthoCamera.fit(self.rig.evaluate(c, vsel), *self.size, margin=0.08)
        # once per fit: drop triangles that face away in the neutral and in every full shape (the back of
        # the head), and triangles outside the view (with a margin)
        shapes = np.concatenate([self.rig.neutral[None], self.rig.neutral + self.rig.deltas])
        self.pivot_ = head_pivot(self.rig)
        R = None if rotations is None or not len(rotations) else np.asarray(rotations, float)
        if R is not None:
            shapes = np.concatenate([shapes, self.pose(self.rig.neutral[None], R[_turn_extremes(R)])])
        tri = self.tri_
        seen = np.zeros(len(tri), bool)
        inview = np.zeros(len(tri), bool)
        w, h = self.size
        cam = self.camera_
        for v in shapes.astype(np.float32):               # loop over shapes (53), not triangles
            x, y = (v[:, 0] - cam.x0) * cam.scale, (cam.y0 - v[:, 1]) * cam.scale     # pixels
            (xa, xb, xc), (ya, yb, yc) = x[tri.T], y[tri.T]
            seen |= (xb - xa) * (yc - ya) - (yb - ya) * (xc - xa) < 0      # counter-clockwise in the mesh's view
            x_lo, x_hi = np.minimum(np.minimum(xa, xb), xc), np.maximum(np.maximum(xa, xb), xc)
            y_lo, y_hi = np.minimum(np.minimum(ya, yb), yc), np.maximum(np.maximum(ya, yb), yc)
            inview |= (x_hi > -0.1 * w) & (x_lo < 1.1 * w) & (y_hi > -0.1 * h) & (y_lo < 1.1 * h)
        keep = np.flatnonzero(seen & inview)
        shown = np.ones(len(keep), bool)
        if self.cull_hidden and curves is not None and len(curves):
            shown = self.visible_triangles(keep, curves, R if R is not None and len(R) == len(curves) else None)
        C = None if curves is None else np.asarray(curves, float)
        moving = np.arange(self.rig.n_shapes) if C is None else np.flatnonzero(np.abs(C).max(axis=0) > 0)
        self._prepare(keep, shown, moving)
        return self

    def visible_triangles(self, candidates: np.ndarray, curves: np.ndarray, rotations: np.ndarray | None = None,
                          n_spread: int = 8, resolution: float | None = None) -> np.ndarray:
        """Which of the triangles ``candidates`` (indices into ``tri_``) some sampled frame shows, grown by one ring.

        The frames sampled: ``n_spread`` spread over ``curves`` (n_frames, n_shapes), those where a shape's curve is
        at its largest and, with ``rotations`` (row i's (3, 3) turn), where a head angle is at an extreme; each goes
        through a z-buffer (:func:`keyshape.base.raster.rasterize`) in :meth:`render`'s painter's order at
        ``resolution`` times the output size (default half, at least 240 pixels, at most the output). A triangle
        sharing a vertex with a shown one is kept too.

        Returns a boolean mask over ``candidates``.
        """
        from keyshape.base.raster import rasterize
        C = np.asarray(curves, float)
        rows = {int(i) for i in np.linspace(0, len(C) - 1, min(len(C), n_spread)).round()}
        moving = np.flatnonzero(np.abs(C).max(axis=0) > 0)
        rows |= set(C[:, moving].argmax(axis=0).tolist())
        if rotations is not None:
            rows |= set(_turn_extremes(rotations).tolist())
        rows = np.array(sorted(rows))
        used = np.unique(self.tri_[candidates])
        local = np.zeros(self.rig.n_vertices, np.intp)
        local[used] = np.arange(len(used))
        V = self.rig.neutral[used] + np.einsum("nk,kvd->nvd", C[rows][:, moving].astype(np.float32),
                                               self.rig.deltas[moving][:, used].astype(np.float32), optimize=True)
        if rotations is not None:
            c = (self.pivot_ if hasattr(self, "pivot_") else head_pivot(self.rig))
            V = np.einsum("nij,nvj->nvi", np.asarray(rotations, float)[rows], V - c, optimize=True) + c
        tri = local[self.tri_[candidates]]
        if resolution is None:
            resolution = min(1.0, max(0.5, 240 / max(self.size)))
        # the painter's order as a depth: a higher layer is nearer than any lower one wherever both cover
        # a pixel; each triangle gets its own three corners (a vertex may be shared across layers)
        layer = self.layer_[self.mat_[candidates]].astype(float)
        corners = np.arange(3 * len(tri)).reshape(-1, 3)
        w, h = self.size
        shown = np.zeros(len(tri), bool)
        for v in V:                                       # loop over sampled frames (a few dozen)
            p = self.camera_.project(v)[tri]              # (n_triangles, 3 corners, 3)
            lift = (np.ptp(p[..., 2]) + 1.0) * layer
            f = rasterize(p[..., :2].reshape(-1, 2) * resolution, (-p[..., 2] - lift[:, None]).ravel(), corners,
                          max(1, round(w * resolution)), max(1, round(h * resolution)))
            shown[f.triangle] = True
        near = np.zeros(len(used), bool)
        near[tri[shown].ravel()] = True
        return near[tri].any(axis=1)

    def _prepare(self, keep: np.ndarray, shown: np.ndarray, moving: np.ndarray) -> None:
        """Index arrays and float32 deltas for :meth:`_draw`: the triangles drawn (``keep[shown]``) and, for
        their vertex normals, every kept triangle around their vertices; the vertices these (and the
        landmarks) use; the moving shapes' deltas at those vertices."""
        tri = self.tri_[keep]
        drawn = tri[shown]
        around = np.zeros(self.rig.n_vertices, bool)
        around[drawn.ravel()] = True
        support = np.concatenate([drawn, tri[~shown & around[tri].any(axis=1)]])
        lm_cols = np.zeros(0, np.intp)
        if self.landmarks is not None:
            lm_cols = np.flatnonzero(np.abs(self.landmarks[0]).sum(axis=0) > 0)
        verts = np.unique(np.concatenate([support.ravel(), lm_cols]))
        local = np.full(self.rig.n_vertices, -1, np.intp)
        local[verts] = np.arange(len(verts))
        self.tri_fit_, self.mat_fit_ = drawn, self.mat_[keep][shown]
        self.verts_, self.moving_ = verts, np.asarray(moving, np.intp)
        self.support_ = local[support]
        # bincount index of each (triangle corner, axis) into the flattened vertex normals
        self.normal_index_ = (self.support_.reshape(-1, 1) * 3 + np.arange(3)).ravel()
        self.base_ = self.rig.neutral[verts].astype(np.float32)
        self.deltas_ = (self.rig.deltas[self.moving_][:, verts]
                        .reshape(len(self.moving_), 3 * len(verts)).astype(np.float32))
        self.lm_ = None
        if self.landmarks is not None:
            self.lm_ = (self.landmarks[0][:, lm_cols].astype(np.float32), local[lm_cols], self.landmarks[1])
        self.layer_fit_ = self.layer_[self.mat_fit_]
        self.colours_ = [tuple(float(x) for x in self.rgb_[k // self.levels] * ((k % self.levels + 0.5) / self.levels))
                         for k in range(len(self.rgb_) * self.levels)]

    def render(self, vertices: np.ndarray) -> np.ndarray:
        """One BGR frame (height, width, 3) of the rig at ``vertices`` (n_vertices, 3)."""
        return self._draw(np.asarray(vertices, np.float32)[self.verts_])

    def _draw(self, v: np.ndarray) -> np.ndarray:
        """One frame from the drawn vertices ``v`` (len(verts_), 3) float32 (the painter's algorithm of the
        module docstring: no loop over triangles, one ``fillPoly`` per (band, material, shade level))."""
        import cv2
        w, h = self.size
        img = np.empty((h, w, 3), np.uint8)
        img[:] = self.background
        sup, nd = self.support_, len(self.tri_fit_)
        if not nd:
            return img
        a, b, c = v[sup[:, 0]], v[sup[:, 1]], v[sup[:, 2]]
        (ux, uy, uz), (wx, wy, wz) = (b - a).T, (c - a).T
        fn = np.stack([uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx], axis=1)     # face normals
        # vertex normals (area weighted) -> per-triangle mean normal, for smooth-looking shading
        vn = np.bincount(self.normal_index_, np.repeat(fn, 3, axis=0).ravel(), minlength=3 * len(v))
        vn = vn.reshape(-1, 3).astype(np.float32)
        vn /= np.maximum(np.sqrt(np.einsum("ij,ij->i", vn, vn)), 1e-12)[:, None]
        t = np.flatnonzero(fn[:nd, 2] > 0)
        tri = sup[t]
        n = vn[tri[:, 0]] + vn[tri[:, 1]] + vn[tri[:, 2]]
        cos = (n @ self.l_) / np.maximum(np.sqrt(np.einsum("ij,ij->i", n, n)), 1e-12)
        lam = np.clip(cos, 0, 1) * (1 - self.ambient) + self.ambient
        level = np.minimum((lam * self.levels).astype(np.int64), self.levels - 1)
        cam = self.camera_
        xy = np.empty((len(v), 2), np.float32)
        xy[:, 0] = (v[:, 0] - np.float32(cam.x0)) * np.float32(cam.scale)
        xy[:, 1] = (np.float32(cam.y0) - v[:, 1]) * np.float32(cam.scale)
        depth = v[tri, 2].sum(axis=1)
        layer = self.layer_fit_[t]
        order = np.lexsort((depth, layer))                          # by layer, then far (small z) first
        layer = layer[order]
        # depth bands of `band` triangles (cut where the layer changes); within one, grouped by colour
        cut = np.zeros(len(t), np.int64)
        cut[np.arange(self.band, len(t), self.band)] = 1
        cut[np.flatnonzero(np.diff(layer)) + 1] = 1
        key = (self.mat_fit_[t] * self.levels + level)[order]
        nkeys = len(self.colours_)
        group = np.cumsum(cut) * nkeys + key
        if group[-1] < 2 ** 15:
            group = group.astype(np.int16)                          # a radix sort
        srt = np.argsort(group, kind="stable")
        group = group[srt]
        pts = np.round(xy * 16).astype(np.int32)[tri[order[srt]]]   # 4 bits of sub-pixel precision
        starts = np.flatnonzero(np.diff(group, prepend=-1))
        for s, e, k in zip(starts.tolist(), [*starts[1:].tolist(), len(group)], (group[starts] % nkeys).tolist()):
            cv2.fillPoly(img, pts[s:e], self.colours_[k], cv2.LINE_8, 4)
        if self.lm_ is not None:
            from keyshape.base.draw import draw_shape
            W, cols, scheme = self.lm_
            p = W @ v[cols]
            img = draw_shape(img, self.camera_.project(p)[:, :2], scheme)
        return img

    def pose(self, vertices: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """``vertices`` (n, n_vertices, 3) turned by the head ``rotations`` (n, 3, 3) about the rig's
        head pivot (:func:`head_pivot`)."""
        c = self.pivot_ if hasattr(self, "pivot_") else head_pivot(self.rig)
        return np.einsum("nij,nvj->nvi", rotations, np.asarray(vertices, float) - c, optimize=True) + c

    def render_curves(self, curves: np.ndarray, rotation: np.ndarray | None = None) -> np.ndarray:
        """One frame of the rig driven by ``curves`` (n_shapes,), turned by the head ``rotation`` (3, 3).

        The deformation is one float32 matrix product of the shapes that move in the fitted curves at
        the vertices drawn (a shape outside them costs the full float64 evaluation of those vertices)."""
        c = np.asarray(curves, float)
        idle = np.ones(self.rig.n_shapes, bool)
        idle[self.moving_] = False
        if c[idle].any():
            v = self.rig.evaluate(c[None], self.verts_)[0].astype(np.float32)
        else:
            v = self.base_ + (c[self.moving_].astype(np.float32) @ self.deltas_).reshape(-1, 3)
        if rotation is not None:
            piv = self.pivot_.astype(np.float32)
            v = (v - piv) @ np.asarray(rotation, np.float32).T + piv
        return self._draw(v)

    def render_many(self, curves: np.ndarray, workers: int | None = None) -> Iterator[np.ndarray]:
        """Yield one frame per row of ``curves`` (n_frames, n_shapes), in order, rendered on ``workers`` threads."""
        for _, img, _ in ordered_map(self.render_curves, ((None, c) for c in np.asarray(curves)), workers):
            yield img


def _turn_extremes(rotations: np.ndarray) -> np.ndarray:
    """Rows of ``rotations`` (n, 3, 3) with the largest and smallest yaw, pitch and roll (about)."""
    R = np.asarray(rotations, float)
    ang = np.stack([R[:, 0, 2], R[:, 1, 2], R[:, 1, 0]], 1)             # sin of yaw, pitch, roll (about)
    return np.unique(np.concatenate([ang.argmin(0), ang.argmax(0)]))


def head_pivot(rig: Rig) -> np.ndarray:
    """The point the rig's head turns about: the centre of its vertices' bounding box, moved back to
    the depth of its rear half (near the top of the neck), so a turn swings the face as a skull does."""
    v = rig.neutral
    lo, hi = v.min(axis=0), v.max(axis=0)
    c = (lo + hi) / 2
    c[2] = lo[2] + 0.4 * (hi[2] - lo[2])
    return c


#: curves CSV columns of the head's rotation, degrees (``keyshape retarget --rig -o curves.csv``)
HEAD_COLUMNS = ("headYaw", "headPitch", "headRoll")


def head_rotations(names, values: np.ndarray) -> np.ndarray | None:
    """(n_frames, 3, 3) head rotations in the rig's frame from a curves table's :data:`HEAD_COLUMNS`
    (degrees; None when it has none), as ``keyshape retarget --tracks`` writes them: yaw > 0 turns the
    face to the subject's left, pitch > 0 looks down, roll > 0 tilts toward the right shoulder,
    ``R = Rz(roll) Ry(yaw) Rx(pitch)`` (:func:`keyshape.decompose.head3d.from_euler`)."""
    from keyshape.decompose.head3d import from_euler
    names = list(names)
    if not any(c in names for c in HEAD_COLUMNS):
        return None
    yaw, pitch, roll = (np.radians(values[:, names.index(c)]) if c in names else np.zeros(len(values))
                        for c in HEAD_COLUMNS)
    return from_euler(yaw, pitch, roll)


def face_square(lo: np.ndarray, hi: np.ndarray, margin: float = 0.45, down: float = 1.0) -> tuple[np.ndarray, float]:
    """Centre and side of the square framing a face whose landmarks span the box ``lo``..``hi`` (2D).

    The box (brows to lips) is grown by ``margin`` of its larger side on every side, and its centre
    moved by 0.15 of its height towards the chin (``down``: +1 where y points down, as in images;
    -1 where y points up, as in a mesh), so forehead and chin are in the frame.
    """
    ext = np.asarray(hi, float) - np.asarray(lo, float)
    centre = (np.asarray(lo, float) + hi) / 2 + [0.0, 0.15 * down * ext[1]]
    return centre, float(max(ext) * (1 + 2 * margin))


def face_crop(points: np.ndarray, success: np.ndarray, size: tuple[int, int], margin: float = 0.45
              ) -> tuple[int, int, int]:
    """One steady square crop ``(x0, y0, side)`` of a take's footage around the tracked face.

    The box spans the 2nd-98th percentiles of the tracked points' extent over the good frames,
    framed by :func:`face_square` and clipped to the image ``size`` (width, height). Fixed over the
    take, so the head's own motion stays visible in the panel.
    """
    w, h = size
    P = np.asarray(points, float)[np.asarray(success, bool)]
    P = P[np.isfinite(P).all(axis=(1, 2))] if len(P) else P
    if not len(P):
        return 0, 0, min(w, h)
    c, side = face_square(np.percentile(P.min(axis=1), 2, axis=0), np.percentile(P.max(axis=1), 98, axis=0), margin)
    side = int(min(round(side), w, h))
    x0 = int(np.clip(round(c[0] - side / 2), 0, w - side))
    y0 = int(np.clip(round(c[1] - side / 2), 0, h - side))
    return x0, y0, side


def caption(img: np.ndarray, text: str) -> np.ndarray:
    """``img`` with ``text`` in its bottom-left corner (white on a dark strip; a contact sheet's
    own caption covers the top)."""
    import cv2
    out = img.copy()
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    y = out.shape[0] - th - 8
    out[y:, : tw + 8] = (out[y:, : tw + 8] * 0.35).astype(np.uint8)
    cv2.putText(out, text, (4, out.shape[0] - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def panel_row(panels: list[np.ndarray]) -> np.ndarray:
    """Panels side by side (each scaled to the first one's height), separated by a thin gap."""
    from functools import reduce

    from keyshape.retarget.output.render import side_by_side
    return reduce(side_by_side, panels)


def default_workers() -> int:
    """Rendering threads: one per core, at most 4 (OpenCV's ``fillPoly`` and numpy release the GIL)."""
    return max(1, min(4, os.cpu_count() or 1))


def ordered_map(fn: Callable[[Any], Any], jobs: Iterable[tuple[Any, Any]], workers: int | None = None
                ) -> Iterator[tuple[Any, Any, float]]:
    """Apply ``fn`` to each ``(tag, x)`` of ``jobs`` on a thread pool; yield ``(tag, fn(x), cpu_seconds)`` in order.

    At most ``2 * workers`` results are pending, so memory stays bounded on long takes and
    a Ctrl-C stops the work within a few frames. ``cpu_seconds`` is the thread CPU time of
    the call (what a progress line reports as the render's own cost).
    """
    workers = default_workers() if workers is None else max(1, int(workers))

    def timed(x):
        t = time.thread_time()
        y = fn(x)
        return y, time.thread_time() - t

    if workers == 1:
        for tag, x in jobs:
            y, dt = timed(x)
            yield tag, y, dt
        return
    pending: deque = deque()
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="keyshape-render") as pool:
        try:
            for tag, x in jobs:
                pending.append((tag, pool.submit(timed, x)))
                if len(pending) >= 2 * workers:
                    tag0, fut = pending.popleft()
                    yield (tag0, *fut.result())
            while pending:
                tag0, fut = pending.popleft()
                yield (tag0, *fut.result())
        finally:
            for _, fut in pending:
                fut.cancel()


def parse_frames(spec: str | None, frames: np.ndarray) -> np.ndarray:
    """Rows of ``frames`` selected by ``A:B`` (frame numbers, B exclusive, either may be empty), all for None."""
    if spec is None:
        return np.arange(len(frames))
    try:
        a, b = (s.strip() for s in spec.split(":"))
        lo = int(a) if a else int(frames.min())
        hi = int(b) if b else int(frames.max()) + 1
    except ValueError:
        raise InputError(f"--frames must be A:B (frame numbers), got {spec!r}") from None
    rows = np.flatnonzero((frames >= lo) & (frames < hi))
    if not len(rows):
        raise InputError(f"--frames {spec}: no frames in that range (the take has {frames.min()}..{frames.max()})")
    return rows


def actor_panel(frame: np.ndarray, points: np.ndarray | None, scheme, success: bool, height: int,
                crop: tuple[int, int, int] | None = None) -> np.ndarray:
    """The footage frame with its contours (``lost`` where tracking failed), cut to ``crop``
    (``x0, y0, side``: :func:`face_crop`) and scaled to ``height``."""
    import cv2

    from keyshape.base.draw import draw_shape
    img = frame.copy()
    if crop is not None:
        x0, y0, side = crop
        img = img[y0: y0 + side, x0: x0 + side]
        if points is not None:
            points = np.asarray(points, float) - (x0, y0)
    if points is not None and success:
        img = draw_shape(img, points, scheme)
    elif not success:
        cv2.putText(img, "lost", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 255), 2)
    s = height / img.shape[0]
    return cv2.resize(img, (max(1, round(img.shape[1] * s)), height), interpolation=cv2.INTER_AREA)
