"""A real clip played K times faster, with its references: does the tracker keep up with fast motion?

Keeps every K-th frame of ``../shared/data/video/CLIP.mp4`` (at the clip's frame rate, so the face moves K
times as far between frames, as in an expressive close-up) and the same frames of its references
(``CLIP_references.npz``, ``CLIP_mediapipe_blendshapes.npz``), so that ``../shared/tools/real_accuracy.py`` and
``rig_fidelity.py`` score the faster clip as they score the clip (docs/tracker.md, "Fast motion"):

    python bench/fast_motion.py franck --every 3 --out /tmp/fast
    keyshape animate /tmp/fast/franck_x3.mp4 --rig ../shared/data/ict-facekit -o /tmp/fast/curves.csv \\
        --livelink /tmp/fast/ll.csv --work /tmp/fast/work
    python ../shared/tools/real_accuracy.py /tmp/fast/work/tracks.csv /tmp/fast/franck_x3_references.npz \\
        --labels /tmp/fast/work/labels
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from keyshape.base.formats.video import VideoReader, video_writer

VIDEOS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "video"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clip", help="a clip of ../shared/data/video with references (franck, cap12_edit, glasses_rom)")
    ap.add_argument("--every", type=int, default=3, help="keep every this many frames (default 3)")
    ap.add_argument("--out", type=Path, required=True, help="folder for the clip and its references")
    a = ap.parse_args()
    if a.every < 1:
        ap.error(f"--every must be at least 1, got {a.every}")
    name = f"{a.clip}_x{a.every}"
    a.out.mkdir(parents=True, exist_ok=True)
    reader = VideoReader(VIDEOS / f"{a.clip}.mp4")
    info = reader.info
    kept = []
    with video_writer(a.out / f"{name}.mp4", info.fps, (info.width, info.height)) as w:
        for i, frame in reader:
            if i % a.every == 0:
                w.write(frame)
                kept.append(i)
    kept = np.array(kept)
    for part in ("references", "mediapipe_blendshapes"):
        z = np.load(VIDEOS / "references" / f"{a.clip}_{part}.npz")
        n = len(z["dlib68"] if "dlib68" in z.files else z["scores"])
        if n != reader.n_read:
            raise SystemExit(f"{a.clip}_{part}.npz: {n} frames, the clip {reader.n_read}")
        np.savez(a.out / f"{name}_{part}.npz", **{k: z[k] if k == "names" else z[k][kept] for k in z.files})
    print(f"{name}: {len(kept)} of {reader.n_read} frames at {info.fps:g} frames/s -> {a.out}")


if __name__ == "__main__":
    main()
