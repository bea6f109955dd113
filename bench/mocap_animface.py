"""Real facial mocap (AnimFace, 41 markers, 60 Hz, mm, no jig) through the marker path onto ICT-FaceKit.

For each clip: the estimated rigid set and its RMS residual; gap filling measured by hiding
10-frame windows of real tracks (5 markers x 4 windows) and comparing the rebuilt positions
with the hidden ones; then the whole clip drives the ICT face skin with planar bones.

    PYTHONPATH=. python bench/mocap_animface.py
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from keyshape.data_synth.mocap import FACE_SKIN, load_facekit  # noqa: E402
from mocap_targets import animface_target_markers  # noqa: E402
from keyshape.retarget.mocap.clean import fill_gaps, remove_rigid_motion  # noqa: E402
from keyshape.retarget.mocap.drive import drive_mesh  # noqa: E402
from keyshape.base.formats.markers import read_trc  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def main():
    kit = load_facekit(DATA / "ict-facekit", ["jawOpen"])
    rng = np.random.default_rng(0)
    for clip in ("jaw", "eyebrows", "cheeks", "nose"):
        take = read_trc(DATA / "mocap" / "animface" / f"{clip}.trc")
        x = take.positions
        rr = remove_rigid_motion(x)
        rigid = [take.labels[i] for i in rr.rigid]
        stab = rr.positions
        hidden = stab.copy()
        truth = []
        for m in rng.choice(len(take.labels), 5, replace=False):
            for s in rng.integers(20, len(x) - 30, 4):
                hidden[s:s + 10, m] = np.nan
                truth.append((m, s))
        filled, rep = fill_gaps(hidden, labels=take.labels)
        err = np.concatenate([np.linalg.norm(filled[s:s + 10, m] - stab[s:s + 10, m], axis=1) for m, s in truth])
        motion = np.concatenate([np.linalg.norm(stab[s:s + 10, m] - stab[0, m], axis=1) for m, s in truth])
        tm = animface_target_markers(kit, take.labels, x[0])
        t0 = time.perf_counter()
        res = drive_mesh(x[::2], take.labels, kit.neutral[:FACE_SKIN], tm)
        dt = time.perf_counter() - t0
        moved = np.linalg.norm(res.vertices - kit.neutral[:FACE_SKIN], axis=2).max() * 10
        print(f"{clip:9s} {len(x)} frames; rigid set {','.join(rigid)} residual RMS {np.mean(rr.residual):.2f} mm; "
              f"gap fill error {err.mean():.2f} mm mean, {np.percentile(err, 95):.2f} p95 "
              f"(markers moved {motion.mean():.2f} mm from frame 0 there); drive {len(res.vertices)} frames "
              f"in {dt:.1f} s, max vertex motion {moved:.1f} mm; {len(res.triangulation.triangles)} bones")


if __name__ == "__main__":
    main()
