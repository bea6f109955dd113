"""The batched torch/kornia tracker against the CPU tracker and the decode ceiling (issue 16 item 5).

Synthesises 640x480 footage (or takes ``--video`` with ``--labels``), trains on its labels and
reports, all measured in the same run: decode-only frames/s; the CPU tracker (decode + track,
one frame at a time); ``track_batch`` on ``--device`` (decode + batched refinement and reading);
the reading alone (``read_batch`` on decoded frames and poses vs the CPU
``Tracker(region_iter=-1).read`` loop, the same whole-face model);
and their ratios. Prints ratios, never asserts times.

    PYTHONPATH=. python bench/bench_torch_tracker.py [--frames 300] [--batch 64] [--passes 3] [--device cpu|cuda]
"""
from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np
from footage import add_footage_args, footage


def main() -> None:
    ap = argparse.ArgumentParser()
    add_footage_args(ap, frames=300)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--passes", type=int, default=3)
    args = ap.parse_args()
    import torch

    from keyshape.base.formats.video import VideoReader
    from keyshape.tracker.commands import fit_model
    from keyshape.tracker.eigenpoints import Pyramid
    from keyshape.tracker.fitting import Tracker
    from keyshape.tracker.torch_batch import read_batch, track_batch

    sync = torch.cuda.synchronize if args.device.startswith("cuda") else (lambda: None)
    with tempfile.TemporaryDirectory() as tmp:
        video, labels, truth_path = footage(args, tmp)
        model = fit_model(video, labels, args.scheme)
        t0 = time.perf_counter()
        frames = np.stack([f for _, f in VideoReader(video)])
        decode = len(frames) / (time.perf_counter() - t0)
        n = len(frames)

        tracker = Tracker(model)
        t0 = time.perf_counter()
        cpu = [tracker.step(f, i) for i, (_, f) in enumerate(VideoReader(video))]
        cpu_fps = n / (time.perf_counter() - t0)
        poses = np.stack([r.pose for r in cpu])

        track_batch(video, model, batch=args.batch, device=args.device, passes=args.passes)        # warm-up (allocations, kernels)
        sync()
        t0 = time.perf_counter()
        pts, _, _, ok = track_batch(video, model, batch=args.batch, device=args.device, passes=args.passes)
        sync()
        gpu_fps = n / (time.perf_counter() - t0)

        # the reading compared with read_batch is the whole-face model's (the torch path reads no region
        # models; the default Tracker reads them too, which differs by up to pixels by design)
        whole = Tracker(model, region_iter=-1)
        t0 = time.perf_counter()
        cpu_read = [whole.read(Pyramid(f), p)[1] for f, p in zip(frames, poses)]
        read_cpu = n / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        got = [read_batch(model, frames[i:i + args.batch], poses[i:i + args.batch], device=args.device)[0]
               for i in range(0, n, args.batch)]
        sync()
        read_gpu = n / (time.perf_counter() - t0)
        diff = np.abs(np.concatenate(got) - np.stack(cpu_read)).max()
        cpu_pts = np.stack([r.points for r in cpu])
        nme = ""
        if truth_path is not None:
            from keyshape.base.formats.tracks import read_tracks
            from keyshape.base.schemes import load_scheme

            truth = read_tracks(truth_path).points
            iod = load_scheme("contours48").interocular_distance(truth)[:, None]
            nme = (f"; NME vs truth: CPU {np.nanmean(np.linalg.norm(cpu_pts - truth, axis=-1) / iod):.4f}, "
                   f"track_batch {np.nanmean(np.linalg.norm(pts - truth, axis=-1) / iod):.4f}")

        print(f"video {video.name}: {n} frames {frames.shape[2]}x{frames.shape[1]}; device {args.device}, "
              f"batch {args.batch}, {args.passes} passes; torch {torch.__version__} with {torch.get_num_threads()} threads")
        print(f"decode only: {decode:.0f} frames/s")
        print(f"CPU tracker (decode + track): {cpu_fps:.0f} frames/s; ratio to decode {cpu_fps / decode:.2f}; "
              f"lost {sum(not r.success for r in cpu)}")
        print(f"track_batch (decode + batched track): {gpu_fps:.0f} frames/s; ratio to decode "
              f"{gpu_fps / decode:.2f}; ratio to the CPU tracker {gpu_fps / cpu_fps:.2f}; "
              f"flagged {int((~ok).sum())}{nme}")
        print(f"reading only (decoded frames, given poses): CPU loop {read_cpu:.0f} frames/s, read_batch "
              f"{read_gpu:.0f} frames/s, ratio {read_gpu / read_cpu:.2f}; max |difference| {diff:.2e} px")


if __name__ == "__main__":
    main()
