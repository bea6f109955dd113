"""Summarise errors.csv files of ``keyshape compare``: the issue's targets in numbers.

Per region over the given files: greedy's RMS against spread's at k = 8, 12, 16;
at how many k spread is below kmeans2, kmeans3 and random; and the median over k
(spread keys) of the target-domain distortions for NNLS and least squares.

Run: ``PYTHONPATH=. python bench/summarize_compare.py bench/results/synth_seed*/errors.csv``
"""
from __future__ import annotations

import csv
import sys
from collections import defaultdict

import numpy as np


def main(paths: list[str]) -> None:
    rows = []
    for p in paths:
        with open(p) as f:
            for r in csv.DictReader(f):
                r["file"] = p
                rows.append(r)
    val = defaultdict(dict)
    for r in rows:
        val[(r["file"], r["region"], r["method"])][int(r["k"])] = r
    regions = list(dict.fromkeys(r["region"] for r in rows))
    for region in regions:
        print(f"== {region}")
        for k in (8, 12, 16):
            g = [float(val[(p, region, "greedy")][k]["rms_px"]) for p in paths if k in val[(p, region, "greedy")]]
            s = [float(val[(p, region, "spread")][k]["rms_px"]) for p in paths if k in val[(p, region, "spread")]]
            if g and s:
                red = [1 - a / b for a, b in zip(g, s)]
                print(f"k={k:2d} rms spread {np.round(s, 4).tolist()} greedy {np.round(g, 4).tolist()} "
                      f"-> greedy lower by {', '.join(f'{100 * x:.0f}%' for x in red)}")
        for other in ("kmeans2", "kmeans3", "random"):
            wins = total = 0
            for p in paths:
                for k, r in val[(p, region, "spread")].items():
                    o = val[(p, region, other)].get(k)
                    if o:
                        total += 1
                        wins += float(r["error"]) < float(o["error"])
            print(f"spread below {other:7s} at {wins}/{total} (file, k) pairs")
        for m in ("spread", "greedy"):
            for col in ("target", "keynoise"):
                a = [float(r[f"{col}_nnls_px"]) for p in paths for r in val[(p, region, m)].values()]
                b = [float(r[f"{col}_lstsq_px"]) for p in paths for r in val[(p, region, m)].values()]
                if a:
                    print(f"{m:7s} {col:8s} distortion median over k: nnls {np.median(a):.3g} px, "
                          f"lstsq {np.median(b):.3g} px; nnls lower at {sum(x < y for x, y in zip(a, b))}/{len(a)}")


if __name__ == "__main__":
    main(sys.argv[1:])
