"""Batched eigen-points tracking with torch and kornia (section 3 of 004_119ba07521a9af0b.txt): many frames per call.

Design notes and figures: docs/scale.md, "Notes on the code", ``tracker/torch_batch.py``.
"""
from __future__ import annotations

import itertools
import math

import numpy as np

from keyshape.base.errors import InputError, KeyshapeError
from keyshape.tracker.eigenpoints import level_sizes

__all__ = ["read_batch", "refine_batch", "track_batch", "require_torch"]


def require_torch():
    """Import and return ``(torch, kornia)``; a :class:`KeyshapeError` telling how to install them if absent."""
    try:
        import torch
        import kornia.geometry.transform  # noqa: F401
        import kornia
    except ImportError as exc:
        raise KeyshapeError(f"the batched (GPU) tracker needs torch and kornia ({exc}): "
                            "pip install keyshape[torch]") from None
    return torch, kornia


def _device(torch, device):
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise KeyshapeError(f"device {device!r}: torch sees no CUDA GPU (use device='cpu')")
    return dev


# --------------------------------------------------------------------------- frames

class _Frames:
    """A batch of frames on the device: gray levels of the Gaussian pyramid, built on demand.

    Level 0 is ``cv2.cvtColor(BGR2GRAY)`` (OpenCV's fixed point: 3735 B + 19235 G + 9798 R,
    15 bits, rounded) and each next level ``cv2.pyrDown`` (5x5 binomial kernel /256, mirrored border
    without repeating the edge, every second pixel, rounded), in integer-exact float32.
    """

    def __init__(self, torch, frames, device, levels: int = 4, full_size=None):
        self.torch = torch
        if isinstance(frames, torch.Tensor):
            t = frames.to(device)
        else:
            arr = _stacked(frames)
            if arr.dtype != np.uint8:
                raise InputError(f"frames: expected uint8 images, got {arr.dtype}")
            t = torch.from_numpy(np.ascontiguousarray(arr)).to(device)
        if t.ndim == 4 and t.shape[-1] == 3:
            # integer sums below 2**24: exact in float32, and faster than int32 on CPU
            w = torch.tensor([3735.0, 19235.0, 9798.0], device=t.device)
            g = torch.floor((t.to(torch.float32) @ w + 16384.0) * (1.0 / 32768.0))
        elif t.ndim == 3:
            g = t.to(torch.float32)
        else:
            raise InputError(f"frames: expected (B, height, width) or (B, height, width, 3), got {tuple(t.shape)}")
        self.levels = [g[:, None]]
        self.n_levels = len(level_sizes(*(g.shape[-2:] if full_size is None else full_size), levels))
        k = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], device=g.device)
        self._kx, self._ky = k[None, None, None, :], k[None, None, :, None]     # separable 5x5 binomial

    def __len__(self) -> int:
        return self.levels[0].shape[0]

    def level(self, lvl: int):
        F = self.torch.nn.functional
        while len(self.levels) <= lvl:
            x = F.pad(self.levels[-1], (2, 2, 2, 2), mode="reflect")
            s = F.conv2d(F.conv2d(x, self._kx, stride=(1, 2)), self._ky, stride=(2, 1))   # integer sums: exact
            self.levels.append(self.torch.floor((s + 128.0) / 256.0))
        return self.levels[lvl]


def _stacked(frames) -> np.ndarray:
    return np.stack([np.asarray(f) for f in frames]) if isinstance(frames, (list, tuple)) else np.asarray(frames)


def _crop(torch, frames, poses: np.ndarray, size: int, device, margin: float = 0.5, levels: int = 4):
    """The frames cut to the region the patches of ``poses`` can reach, as :class:`_Frames`.

    Only the face region is converted and downsampled (as :meth:`Pyramid.window` does on
    the CPU): the crop's corner is a multiple of the coarsest level's pixel and it keeps
    a margin of ``margin`` times the face's extent plus the pyrDown kernels' reach, so the pixels a
    warp reads are those of the whole frame's levels. Returns ``(frames, (x0, y0))``;
    poses and points are shifted by the corner.
    """
    if isinstance(frames, torch.Tensor):                  # already on the device: used whole
        return _Frames(torch, frames, device, levels), (0, 0)
    arr = _stacked(frames)
    if arr.ndim not in (3, 4) or len(arr) != len(poses) or not np.isfinite(poses).all():
        return _Frames(torch, arr, device, levels), (0, 0)
    H, W = arr.shape[1:3]
    n = len(level_sizes(H, W, levels))
    corners = np.array([[0, 0, 1], [size, 0, 1], [0, size, 1], [size, size, 1]], np.float64)
    pts = np.einsum("bij,kj->bki", poses, corners).reshape(-1, 2)
    lo, hi = pts.min(0), pts.max(0)
    step = 2 ** (n - 1)
    m = margin * (hi - lo) + 6 * step + 4
    x0 = max(int(math.floor((lo[0] - m[0]) / step)) * step, 0)
    y0 = max(int(math.floor((lo[1] - m[1]) / step)) * step, 0)
    x1, y1 = min(int(math.ceil(hi[0] + m[0])), W), min(int(math.ceil(hi[1] + m[1])), H)
    if x1 - x0 < 64 or y1 - y0 < 64:
        return _Frames(torch, arr, device, levels), (0, 0)
    return _Frames(torch, arr[:, y0:y1, x0:x1], device, levels, full_size=(H, W)), (x0, y0)


def _warp(torch, kornia, frames: _Frames, poses, size: int):
    """``warp_patch_u8`` for every frame: (B, size, size) float32 holding uint8 values.

    ``poses`` (B, 2, 3) float64 tensor, ``image_from_model`` (of the patch of this ``size``).
    """
    from kornia.geometry.transform import warp_affine

    a = poses
    det = (a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]).abs().sqrt()
    # pyramid level as warp_patch_u8: floor(log2(scale / 1.5)) + 1 where scale > 1.5
    lv = torch.where(det > 1.5, torch.floor(torch.log2(det / 1.5)) + 1, torch.zeros_like(det))
    lv = lv.clamp(0, frames.n_levels - 1).to(torch.int64)
    out = torch.empty((len(a), size, size), dtype=torch.float32, device=a.device)
    for lvl in torch.unique(lv).tolist():
        sel = (lv == lvl).nonzero().squeeze(1)
        al = a[sel].clone()
        if lvl:
            f = 0.5 ** lvl
            al = al * f
            al[:, :, 2] += 0.5 * f - 0.5
        # kornia takes the forward (image -> patch) map: invert image_from_model (in float64)
        lin = al[:, :, :2]
        inv = torch.linalg.inv(lin)
        m = torch.cat([inv, -(inv @ al[:, :, 2:])], dim=2).to(torch.float32)
        src = frames.level(lvl).index_select(0, sel)
        w = warp_affine(src, m, (size, size), mode="bilinear", padding_mode="border", align_corners=True)
        out[sel] = torch.round(w[:, 0]).clamp_(0, 255)
    return out


# --------------------------------------------------------------------------- reading

def _as_poses(torch, poses, n, dev):
    p = torch.as_tensor(np.asarray(poses, np.float64) if not isinstance(poses, torch.Tensor) else poses,
                        dtype=torch.float64, device=dev)
    if p.shape != (n, 2, 3):
        raise InputError(f"poses: expected ({n}, 2, 3) image_from_model affines, got {tuple(p.shape)}")
    return p


def _read(torch, kornia, model, fr: _Frames, poses):
    """Model-frame shapes (B, n_points, 2), image points and residuals (B,) at ``poses`` (tensors)."""
    rd = model.reading_
    dev = poses.device
    idx = torch.as_tensor(model.index_, device=dev)
    e, _ = _normalised(torch, _warp(torch, kornia, fr, poses, model.patch_size_), idx)
    e = e - torch.as_tensor(rd.mean_i, device=dev)
    # [coefficients | U_Iᵀe] of every frame in one product: e (B, n_pix) @ [pinv_iᵀ | U_I]
    k = len(rd.pinv_i)
    mat = torch.as_tensor(np.hstack([rd.pinv_i.T, rd.basis_i]), device=dev)
    cu = e @ mat
    c, ue = cu[:, :k], cu[:, k:]
    gram = torch.as_tensor(rd.basis_i.T @ rd.basis_i, device=dev)
    r = ((e * e).sum(1) - 2 * (c * ue).sum(1) + ((c @ gram) * c).sum(1)).clamp_min(0) / e.shape[1]
    shape = (torch.as_tensor(rd.mean_l, device=dev) + c @ torch.as_tensor(rd.basis_l.T, device=dev))
    shape = shape.reshape(len(c), -1, 2)
    pts = shape @ poses[:, :, :2].transpose(1, 2) + poses[:, None, :, 2]
    return shape, pts, r


def read_batch(model, frames, poses, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Eigen-points reading of ``B`` frames at once (the batched :meth:`Tracker.read`).

    Parameters
    ----------
    model : fitted :class:`~keyshape.tracker.eigenpoints.AppearanceModel`
    frames : (B, H, W) or (B, H, W, 3) uint8 (gray or BGR), an array, a list or a torch tensor
    poses : (B, 2, 3) ``image_from_model`` affines
    device : torch device (``"cpu"``, ``"cuda"``)

    Returns
    -------
    points : (B, n_points, 2) image landmarks, as ``model.predict(frame, pose)`` (within ~1e-3 px)
    residuals : (B,) appearance residuals (mean squared normalised intensity error)
    """
    torch, kornia = require_torch()
    model._check_fitted()
    dev = _device(torch, device)
    with torch.no_grad():
        fr, off, p = _cropped(torch, model, frames, poses, dev, 0.0)
        _, pts, r = _read(torch, kornia, model, fr, p)
    return pts.cpu().numpy() + off, r.cpu().numpy()


def _cropped(torch, model, frames, poses, dev, margin: float):
    """:func:`_crop`'s frames and corner, and ``poses`` as a tensor in the crop's pixels."""
    poses = np.array(poses, np.float64)
    fr, (x0, y0) = _crop(torch, frames, poses, model.patch_size_, dev, margin=margin)
    p = _as_poses(torch, poses, len(fr), dev)
    p[:, :, 2] -= torch.tensor([x0, y0], dtype=torch.float64, device=dev)
    return fr, (x0, y0), p


# --------------------------------------------------------------------------- refinement

class _LevelOps:
    """A tracker level's constant arrays (:class:`keyshape.tracker.fitting._Level`) as tensors."""

    def __init__(self, torch, lv, dev):
        t = lambda a: torch.as_tensor(np.asarray(a, np.float64), device=dev)  # noqa: E731
        self.size = lv.size
        self.index = torch.as_tensor(lv.index, device=dev)
        self.template = t(lv.template)
        self.update = t(lv.update)
        self.to_fine = t(lv.to_fine)
        self.level_from_fine = t(lv.level_from_fine)
        self.q = t(lv.q)
        self.xx, self.yy = t(lv.xx), t(lv.yy)


def _compose(outer, inner):
    """Batched ``compose_affine``: (B, 2, 3) or (2, 3) operands."""
    lin = outer[..., :2] @ inner[..., :2]
    tr = outer[..., :2] @ inner[..., 2:] + outer[..., 2:]
    import torch

    return torch.cat([lin, tr], dim=-1)


def _clamp(torch, a, max_aniso: float):
    """Batched ``Tracker._clamp``: limit the singular-value ratio of the linear part."""
    lin = a[:, :, :2]
    det = (lin[:, 0, 0] * lin[:, 1, 1] - lin[:, 0, 1] * lin[:, 1, 0]).abs()
    fro = (lin * lin).sum((1, 2))
    disc = (fro * fro - 4 * det * det).clamp_min(0).sqrt()
    over = (fro + disc) > max_aniso ** 2 * (fro - disc).clamp_min(1e-300)
    if not bool(over.any()):
        return a
    u, sv, vt = torch.linalg.svd(lin)
    g = (sv[:, 0] * sv[:, 1]).sqrt()
    r = math.sqrt(max_aniso)
    s = torch.stack([g * r, g / r], 1)
    fixed = u @ torch.diag_embed(s) @ vt
    out = a.clone()
    out[:, :, :2] = torch.where(over[:, None, None], fixed, lin)
    return out


def _normalised(torch, patch, index):
    flat = patch.reshape(len(patch), -1).index_select(1, index).to(torch.float64)
    e = flat - flat.mean(1, keepdim=True)
    sd = e.pow(2).mean(1, keepdim=True).sqrt().clamp_min(1e-6)
    return e / sd, sd


def _step_affine(torch, d):
    """The (B, 2, 3) affines ``identity + step`` of the steps ``d`` (B, 6) (column-major parameters)."""
    return torch.stack([torch.stack([1 + d[:, 0], d[:, 2], d[:, 4]], 1),
                        torch.stack([d[:, 1], 1 + d[:, 3], d[:, 5]], 1)], 1)


def _align_level(torch, kornia, fr, a, lv: _LevelOps, n_iter: int, max_aniso: float):
    """Inverse-compositional steps of ``Tracker.align`` at one level, every frame in parallel."""
    al = _compose(a, lv.to_fine)
    active = torch.ones(len(a), dtype=torch.bool, device=a.device)
    its = torch.zeros(len(a), dtype=torch.int64, device=a.device)
    for _ in range(n_iter):
        if not bool(active.any()):
            break
        v, _ = _normalised(torch, _warp(torch, kornia, fr, al, lv.size), lv.index)
        dp = (v - lv.template) @ lv.update.T                    # (B, 6)
        w = _step_affine(torch, dp)
        winv_lin = torch.linalg.inv(w[:, :, :2])
        winv = torch.cat([winv_lin, -(winv_lin @ w[:, :, 2:])], 2)
        new = _clamp(torch, _compose(al, winv), max_aniso)
        al = torch.where(active[:, None, None], new, al)
        its += active
        done = (dp[:, 4:].abs().amax(1) < 0.03) & (dp[:, :4].abs().amax(1) < 1e-3)
        active = active & ~done
    return _compose(al, lv.level_from_fine), its


def _polish(torch, kornia, fr, a, lv: _LevelOps, n_polish: int, max_aniso: float):
    """``Tracker.polish`` for every frame in parallel (same steps, same acceptance and stopping)."""
    F = torch.nn.functional
    B, n = len(a), len(lv.index)
    dev = a.device
    active = torch.ones(B, dtype=torch.bool, device=dev)
    its = torch.zeros(B, dtype=torch.int64, device=dev)
    best_r = torch.full((B,), math.inf, dtype=torch.float64, device=dev)
    prev = a
    sob = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], device=dev)
    kern = torch.stack([sob, sob.T])[:, None]                    # d/dx, d/dy (3x3 Sobel, unscaled)
    xx, yy, one = lv.xx, lv.yy, torch.ones_like(lv.xx)
    for _ in range(n_polish):
        if not bool(active.any()):
            break
        patch = _warp(torch, kornia, fr, a, lv.size)
        e, sd = _normalised(torch, patch, lv.index)
        e = e - lv.template
        qe = e @ lv.q                                            # (B, k')
        r = ((e * e).sum(1) - (qe * qe).sum(1)).clamp_min(0) / n
        worse = active & (r >= best_r)
        a = torch.where(worse[:, None, None], prev, a)           # a step that did not lower r is undone
        active = active & ~worse
        best_r = torch.where(active, r, best_r)
        prev = a
        # cv2.spatialGradient: 3x3 Sobel with the mirrored (reflect-101) border
        g = F.conv2d(F.pad(patch[:, None], (1, 1, 1, 1), mode="reflect"), kern)
        g = g.reshape(B, 2, -1).index_select(2, lv.index).to(torch.float64) / (8.0 * sd[:, :, None])
        gx, gy = g[:, 0], g[:, 1]
        jac = torch.stack([gx * xx, gy * xx, gx * yy, gy * yy, gx * one, gy * one], 2)   # (B, n, 6)
        jtj = jac.transpose(1, 2) @ jac
        jte = (jac * e[:, :, None]).sum(1)
        qj = lv.q.T @ jac                                        # (B, k', 6)
        hess = jtj - qj.transpose(1, 2) @ qj + 1e-9 * torch.eye(6, dtype=torch.float64, device=dev)
        rhs = (qj * qe[:, :, None]).sum(1) - jte
        d = torch.linalg.solve(hess, rhs[:, :, None])[:, :, 0]
        new = _clamp(torch, _compose(a, _step_affine(torch, d)), max_aniso)
        a = torch.where(active[:, None, None], new, a)
        its += active
        done = (d[:, 4:].abs().amax(1) < 0.01) & (d[:, :4].abs().amax(1) < 3e-4)
        active = active & ~done
    return a, its


def _refine(torch, kornia, tracker, fr, poses, levels, n_iter, dev):
    ops = getattr(tracker, "_torch_ops", None)
    if ops is None or ops[0] != dev:
        ops = (dev, [_LevelOps(torch, lv, dev) for lv in tracker.levels])
        tracker._torch_ops = ops
    a = poses
    its = torch.zeros(len(a), dtype=torch.int64, device=dev)
    for li in levels:
        a, k = _align_level(torch, kornia, fr, a, ops[1][li], n_iter, tracker.max_anisotropy)
        its += k
    if tracker.n_polish:
        a, k = _polish(torch, kornia, fr, a, ops[1][-1], tracker.n_polish, tracker.max_anisotropy)
        its += k
    return a, its


def refine_batch(model, frames, poses, n_iter: int = 5, levels=(0,), n_polish: int = 3,
                 device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Refine ``B`` poses at once: :meth:`Tracker.align` applied to every frame in parallel (frame by frame what
    ``Tracker(model, n_iter=n_iter, n_polish=n_polish).align(Pyramid(frame), pose, levels)`` gives, up to the
    warp's sub-grey-level differences; ``levels`` 0: the half-resolution level, 1: full resolution, ``()``: none).

    Parameters
    ----------
    model : fitted AppearanceModel
    frames : (B, H, W) or (B, H, W, 3) uint8
    poses : (B, 2, 3) starting ``image_from_model`` affines
    n_iter, levels, n_polish : as :class:`~keyshape.tracker.fitting.Tracker` and its ``align``
    device : torch device

    Returns
    -------
    poses : (B, 2, 3) refined affines
    iterations : (B,) steps taken per frame
    """
    torch, kornia = require_torch()
    from keyshape.tracker.fitting import Tracker

    tracker = Tracker(model, n_iter=n_iter, n_polish=n_polish, search=False, region_iter=-1)
    dev = _device(torch, device)
    with torch.no_grad():
        fr, off, p = _cropped(torch, model, frames, poses, dev, 0.2)
        a, its = _refine(torch, kornia, tracker, fr, p, tuple(levels), int(n_iter), dev)
    a = a.cpu().numpy()
    a[:, :, 2] += off
    return a, its.cpu().numpy()


# --------------------------------------------------------------------------- offline tracking

def track_batch(video, model, batch: int = 64, device: str = "cpu", n_iter: int = 5, passes: int = 3,
                start_pose=None, crop_margin: float = 0.5):
    """Track a whole video offline, ``batch`` frames per tensor call (the GPU path; docs/tracker.md, "Batched torch
    path"): the first frame by the CPU tracker unless ``start_pose`` is given, then ``passes`` refinements per
    batch; no lost-track recovery (a frame above the lost threshold has ``success`` False and keeps its pose).

    Parameters
    ----------
    video : path of a video file, or an iterable of uint8 frames
    model : fitted AppearanceModel
    batch : frames per batch
    device : ``"cpu"`` or ``"cuda"`` (torch device)
    n_iter : alignment steps per level in pass 1
    passes : refinement passes per batch (>= 1)
    start_pose : (2, 3) ``image_from_model`` of the first frame (None: found by the CPU tracker)
    crop_margin : each batch is processed in a crop of its frames around the previous batch's
        last face, with this fraction of the face's extent added on each side (a face that
        moves further within one batch leaves the crop: use a larger margin or smaller batches)

    Returns
    -------
    points : (n_frames, n_points, 2)
    poses : (n_frames, 2, 3)
    residuals : (n_frames,)
    success : (n_frames,) bool (residual below the tracker's lost threshold)
    """
    torch, kornia = require_torch()
    from keyshape.tracker.fitting import Tracker

    model._check_fitted()
    if batch < 1 or passes < 1:
        raise InputError(f"batch and passes must be >= 1, got {batch} and {passes}")
    dev = _device(torch, device)
    tracker = Tracker(model, n_iter=n_iter, search=True, region_iter=-1)
    if isinstance(video, (str, bytes)) or hasattr(video, "__fspath__"):
        from keyshape.base.formats.video import VideoReader

        frames_iter = (f for _, f in VideoReader(video))
    else:
        frames_iter = iter(video)
    pts_all, poses_all, res_all = [], [], []
    last = None if start_pose is None else np.asarray(start_pose, np.float64)
    with torch.no_grad():
        while chunk := list(itertools.islice(frames_iter, batch)):
            if last is None:
                res = tracker.step(chunk[0])
                if not res.success:
                    raise KeyshapeError("track_batch: the CPU tracker did not find the face in the first frame")
                last = res.pose
            b = len(chunk)
            # only the face region (with a margin for the motion within the batch) is converted,
            # downsampled and warped; poses are in that crop's pixels until they are returned
            fr, off = _crop(torch, np.stack(chunk), np.repeat(last[None], b, 0), model.patch_size_, dev,
                            margin=crop_margin)
            last = last.copy()
            last[:, 2] -= off
            start = torch.as_tensor(last, dtype=torch.float64, device=dev).expand(b, 2, 3).contiguous()
            a, _ = _refine(torch, kornia, tracker, fr, start, (0,), n_iter, dev)
            first = torch.as_tensor(last, dtype=torch.float64, device=dev)[None]
            for _ in range(passes - 1):
                a, _ = _refine(torch, kornia, tracker, fr, torch.cat([first, a[:-1]]), (), n_iter, dev)
            _, pts, r = _read(torch, kornia, model, fr, a)
            pts_all.append(pts.cpu().numpy() + off)
            a = a.cpu().numpy()
            a[:, :, 2] += off
            poses_all.append(a)
            res_all.append(r.cpu().numpy())
            last = poses_all[-1][-1]
    if not pts_all:
        n = model.n_points
        return np.empty((0, n, 2)), np.empty((0, 2, 3)), np.empty(0), np.empty(0, bool)
    res = np.concatenate(res_all)
    return np.concatenate(pts_all), np.concatenate(poses_all), res, res < tracker.lost_threshold
