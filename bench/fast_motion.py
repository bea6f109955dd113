"""A real clip played K times faster, or as a close-up, with its references: does keyshape keep up?

Keeps every K-th frame of ``../shared/data/video/CLIP.mp4`` (at the clip's frame rate, so the face moves K
times as far between frames, as in an expressive close-up) and the same frames of its references
(``CLIP_references.npz``, ``CLIP_mediapipe_blendshapes.npz``), so that ``../shared/tools/real_accuracy.py`` and
``rig_fidelity.py`` score the faster clip as they score the clip (docs/tracker.md, "Fast motion"). ``--zoom Z``
also enlarges each frame Z times about the face (a fixed crop centred on the median of dlib's reference points,
kept inside the frame; the reference points mapped with it): a close-up whose face fills the frame and reaches
past its edges (docs/label.md, "Close-ups"). Output ``CLIP_xK.mp4`` (``CLIP_zZxK.mp4`` with ``--zoom``):

    python bench/fast_motion.py franck --every 3 --out /tmp/fast
    keyshape animate /tmp/fast/franck_x3.mp4 --rig ../shared/data/ict-facekit -o /tmp/fast/curves.csv \\
        --livelink /tmp/fast/ll.csv --work /tmp/fast/work
    python ../shared/tools/real_accuracy.py /tmp/fast/work/tracks.csv /tmp/fast/franck_x3_references.npz \\
        --labels /tmp/fast/work/labels
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from keyshape.base.formats.video import VideoReader, video_writer

VIDEOS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "video"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clip", help="a clip of ../shared/data/video with references (franck, cap12_edit, glasses_rom)")
    ap.add_argument("--every", type=int, default=3, help="keep every this many frames (default 3)")
    ap.add_argument("--zoom", type=float, default=1.0, help="enlarge each frame this many times about the face")
    ap.add_argument("--out", type=Path, required=True, help="folder for the clip and its references")
    a = ap.parse_args()
    if a.every < 1 or a.zoom < 1:
        ap.error(f"--every and --zoom must be at least 1, got {a.every} and {a.zoom}")
    name = f"{a.clip}_x{a.every}" if a.zoom == 1 else f"{a.clip}_z{a.zoom:g}x{a.every}"
    a.out.mkdir(parents=True, exist_ok=True)
    reader = VideoReader(VIDEOS / f"{a.clip}.mp4")
    info = reader.info
    refs = dict(np.load(VIDEOS / "references" / f"{a.clip}_references.npz"))
    w, h, z = info.width, info.height, a.zoom
    x0, y0 = np.clip(np.median(refs["dlib68"].reshape(-1, 2), 0) - (w / z / 2, h / z / 2), 0, (w - w / z, h - h / z))
    zoom = np.array([[z, 0, -z * x0], [0, z, -z * y0]])                 # the close-up from the frame
    kept = []
    with video_writer(a.out / f"{name}.mp4", info.fps, (w, h)) as out:
        for i, frame in reader:
            if i % a.every == 0:
                out.write(frame if z == 1 else cv2.warpAffine(frame, zoom, (w, h), flags=cv2.INTER_LINEAR))
                kept.append(i)
    kept = np.array(kept)
    for part in ("references", "mediapipe_blendshapes"):
        d = refs if part == "references" else dict(np.load(VIDEOS / "references" / f"{a.clip}_{part}.npz"))
        n = len(d["dlib68"] if "dlib68" in d else d["scores"])
        if n != reader.n_read:
            raise SystemExit(f"{a.clip}_{part}.npz: {n} frames, the clip {reader.n_read}")
        d = {k: v if k == "names" else v[kept] for k, v in d.items()}
        if part == "references":
            d = {k: (v * z + zoom[:, 2]).astype(v.dtype) for k, v in d.items()}
        np.savez(a.out / f"{name}_{part}.npz", **d)
    print(f"{name}: {len(kept)} of {reader.n_read} frames at {info.fps:g} frames/s -> {a.out}")


if __name__ == "__main__":
    main()
