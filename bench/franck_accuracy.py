"""Tracker accuracy on real footage against dlib (issue 3): franck.mp4, ibug68, 12 labels.

dlib's 68-point predictor labels every frame (cached); 12 frames spread evenly
over the video are the training labels; the tracker follows all 4,800 frames
and its points are compared with dlib's per frame (NME over dlib's inter-ocular
distance), per region, with the longest run of lost frames and a contact sheet.

    PYTHONPATH=.:bench python bench/franck_accuracy.py [--sheet franck_sheet.png] [--cache /tmp/franck_dlib.npy]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

VIDEO = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "video" / "franck.mp4"


def longest_run(mask: np.ndarray) -> int:
    best = cur = 0
    for v in mask:
        cur = cur + 1 if v else 0
        best = max(best, cur)
    return best


def evaluate(video=VIDEO, cache=None, n_labels: int = 12, sheet=None) -> dict:
    from dlib_points import label_video
    from keyshape.tracker.commands import fit_model, track_video
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.formats.labels import write_labels
    from keyshape.base.schemes import load_scheme

    dl = label_video(video, cache)
    n = len(dl)
    idx = np.linspace(0, n - 1, n_labels).round().astype(int)
    sch = load_scheme("ibug68")
    with tempfile.TemporaryDirectory() as tmp:
        write_labels(Path(tmp) / "labels", idx, dl[idx])
        t0 = time.perf_counter()
        model = fit_model(video, Path(tmp) / "labels", "ibug68")
        t_train = time.perf_counter() - t0
        summ = track_video(video, model, Path(tmp) / "tracks.csv", show_progress=False)
        tr = read_tracks(Path(tmp) / "tracks.csv")
    iod = sch.interocular_distance(dl)
    d = np.linalg.norm(tr.points - dl, axis=-1) / iod[:, None]
    out = {"train_s": t_train, "fps": summ.fps, "lost": int((~tr.success).sum()),
           "longest_lost_run": longest_run(~tr.success), "nme": {"all": d.mean(1)}}
    for name, ids in sch.regions.items():
        out["nme"][name] = d[:, list(ids)].mean(1)
    if sheet is not None:
        import cv2

        from keyshape.base.draw import contact_sheet, crop_around, draw_shape
        from keyshape.base.formats.video import VideoReader

        picks = set(np.linspace(0, n - 1, 24).round().astype(int).tolist())
        picks |= set(np.argsort(-np.nan_to_num(out["nme"]["all"], nan=1.0))[:4].tolist())
        imgs, caps = [], []
        for i, f in VideoReader(video):
            if i in picks:
                im = draw_shape(f, dl[i], sch, colour=(0, 0, 255))
                im = draw_shape(im, tr.points[i], sch) if tr.success[i] else im
                crop, _ = crop_around(im, dl[i], margin=0.3)
                imgs.append(crop)
                caps.append(f"{i} nme {out['nme']['all'][i]:.3f}" if tr.success[i] else f"{i} lost")
        cv2.imwrite(str(sheet), contact_sheet(imgs, caps, columns=7, tile_width=200))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--video", default=str(VIDEO))
    ap.add_argument("--cache", default=None, help=".npy cache of dlib's points for every frame")
    ap.add_argument("--sheet", default=None, help="write a contact sheet PNG (red: dlib, colours: tracker)")
    args = ap.parse_args()
    r = evaluate(Path(args.video), args.cache, sheet=args.sheet)
    print(f"train {r['train_s']:.1f} s; track {r['fps']:.0f} frames/s; lost {r['lost']} frames, "
          f"longest lost run {r['longest_lost_run']}")
    for name, e in r["nme"].items():
        print(f"  {name:6s} NME vs dlib: mean {np.nanmean(e):.4f}  p95 {np.nanpercentile(e, 95):.4f}  "
              f"worst {np.nanmax(e):.4f} (frame {int(np.nanargmax(e))})")


if __name__ == "__main__":
    main()
