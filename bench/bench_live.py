"""Speed of ``keyshape live`` at 640x480 (issue 25: sustained >= 30 frames/s, median latency < 15 ms).

A synthetic 640x480 take (``keyshape.data_synth``) is the camera; the chain is the one ``keyshape live``
runs (model trained on the take's suggested frames, a 4-key set, the toy rig of the tests with its pose
library; the 3D head and gaze calibrated on the take's own tracks, as ``keyshape live`` does by default), and
the packets go to a UDP socket on 127.0.0.1 that drains them. Three runs:

* **paced**: the video played at its own 30 frames/s, as a camera delivers it; reports the frames/s
  sustained, frames lost (dropped because the chain fell more than a frame behind) and the latency
  from a frame's capture (the moment it is due) to its packet sent: median and 95th percentile;
* **unpaced** (``--no-pace``): frames as fast as they decode: the chain's throughput ceiling and its
  per-frame latency (decode excluded: a frame counts as captured once decoded);
* **unpaced, 2D head** (``load_chain(head="2d")``): the same without the 3D head and gaze, for their cost.

Each line carries the 1-minute load average read right after its run (the machine may be shared).

    python bench/bench_live.py [--frames 600] [--work DIR]
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import socket
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def prepare(work: Path, frames: int) -> Path:
    """The take and the offline pieces (reused when ``work`` already has them)."""
    from keyshape.cli import main
    from keyshape.data_synth.video import synthesize
    if (work / "poses.json").is_file():
        return work
    out = synthesize(work / "synth", frames=frames, seed=3, labels=12)
    spec = importlib.util.spec_from_file_location("trp", REPO / "tests" / "test_rig_poses.py")
    trp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(trp)
    rig, lm = trp.write_toy_rig(work / "rig")
    for s in (["train", str(out["video"]), "--labels", str(out["labels"]), "-o", str(work / "model.npz")],
              ["track", str(out["video"]), "--model", str(work / "model.npz"), "-o", str(work / "t.csv"), "--quiet"],
              ["select", str(work / "t.csv"), "-k", "4", "-o", str(work / "k.json")],
              ["pose", str(work / "k.json"), "--rig", str(rig), "--landmarks", str(lm), "-o", str(work / "poses.json")]):
        assert main(s) == 0, s
    os.replace(out["video"], work / "take.mp4")
    return work


def run(work: Path, pace: bool, head: str = "3d") -> dict:
    from keyshape.live import FrameSource, LiveLinkSender, load_chain, stream
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.settimeout(2.0)
    got = []

    def drain():
        try:
            while True:
                got.append(len(sink.recv(4096)))
        except OSError:
            pass
    from keyshape.retarget.defaults import SolveOptions
    model, chain = load_chain(work / "model.npz", work / "k.json", [str(work / "rig")], head=head,
                              options=SolveOptions(landmarks=str(work / "toy_landmarks.json")), say=lambda line: None)
    th = threading.Thread(target=drain, daemon=True)        # after the calibration: it waits 2 s at most
    th.start()
    sender = LiveLinkSender("127.0.0.1", sink.getsockname()[1])
    src = FrameSource(str(work / "take.mp4"), pace=pace)
    c0 = time.process_time()
    stats = stream(src, model, chain, sender, status=None)
    cpu = time.process_time() - c0
    sender.close()
    th.join()
    sink.close()
    lat = np.array(stats.latencies) * 1e3
    return {"frames": stats.frames, "received": len(got), "fps": stats.fps, "lost": stats.lost,
            "latency_median_ms": float(np.median(lat)), "latency_p95_ms": float(np.percentile(lat, 95)),
            "cpu_s_per_frame_ms": 1e3 * cpu / max(stats.frames, 1), "load": os.getloadavg()[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=600, help="length of the synthetic take (default 600)")
    ap.add_argument("--work", default=None, help="folder for the take and model (default: a temporary one)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(a.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        prepare(work, a.frames)
        print(f"keyshape live at 640x480, {a.frames} frames, {os.cpu_count()} CPUs, load average "
              f"{os.getloadavg()[0]:.2f}")
        runs = ((True, "3d", "paced (30 fps video as a camera)"), (False, "3d", "unpaced (--no-pace)"),
                (False, "2d", "unpaced, 2D head (load_chain(head=\"2d\"))"))
        for pace, head, label in runs:
            r = run(work, pace, head)
            print(f"{label:34s} {r['fps']:6.1f} frames/s  lost {r['lost']:3d}  latency median "
                  f"{r['latency_median_ms']:5.1f} ms p95 {r['latency_p95_ms']:5.1f} ms  CPU "
                  f"{r['cpu_s_per_frame_ms']:.1f} ms/frame  ({r['frames']} sent, {r['received']} received; "
                  f"load average {r['load']:.2f})")


if __name__ == "__main__":
    main()
