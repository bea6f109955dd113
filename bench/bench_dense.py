"""Benchmark of the dense-mesh tools on ICT-FaceKit (issue 7): registration accuracy and speed,
key-point insertion tables (002's Tables 1-2),
facial transfer (002 section 6). Prints a markdown report; no timed asserts.

    PYTHONPATH=. /work/venv/bin/python bench/bench_dense.py [--quick]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from dense_synth import LANDMARKS68, PERFORMANCES, dense_sequence, realistic_face
from keyshape.retarget.dense.keypoints import KeyPointInserter, random_insertion, sequence_errors
from keyshape.retarget.dense.registration import place_markers, register_mesh
from keyshape.retarget.dense.transfer import transfer_sequence
from keyshape.base.formats.obj import read_obj, read_obj_vertices

ICT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ict-facekit"
SKIN = np.arange(9409)


def mm(a, b):
    d = np.linalg.norm(a[SKIN] - b[SKIN], axis=1) * 10.0
    return d.mean(), np.percentile(d, 95)


def bench_registration(quick):
    ref = read_obj(ICT / "generic_neutral_mesh.obj")
    tri = ref.triangles
    vi = json.loads((ICT / "vertex_indices.json").read_text())
    lm68 = np.array(vi["idx_to_landmark_verts"])
    ids = [read_obj_vertices(ICT / f"identity00{i}.obj") for i in range(4)]
    targets = [(f"identity00{i}", ids[i]) for i in range(4)] + [(f"realistic (seed {s})", realistic_face(
        ref.vertices, ids, s)) for s in (0, 1)]
    if quick:
        targets = targets[1:2]
    pairs = [{"reference": int(lm68[i]), "target": int(lm68[i])} for i in LANDMARKS68]
    markers = {str(i): int(v) for i, v in enumerate(lm68)}
    print("\n### Registration of generic_neutral_mesh.obj (26,719 vertices), face skin 0-9408, mm\n")
    print("| target | solver | warp mean | warp p95 | fitted mean | fitted p95 | mean cut | markers mean | time s | evals |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, tv in targets:
        solvers = ["lbfgs", "simplex"] if name == "identity001" else ["lbfgs"]
        for solver in solvers:
            res = register_mesh(ref.vertices, tri, tv, tri, pairs, solver=solver)
            w, f = mm(res.warped, tv), mm(res.vertices, tv)
            placed = place_markers(markers, ref.vertices, tri, res.vertices, tv, tri)
            mk = np.mean([np.linalg.norm(np.array(placed[k]["position"]) - tv[v]) * 10 for k, v in markers.items()])
            print(f"| {name} | {solver} | {w[0]:.2f} | {w[1]:.2f} | {f[0]:.2f} | {f[1]:.2f} | {w[0] / f[0]:.2f}x "
                  f"| {mk:.2f} | {res.seconds:.1f} | {res.n_evals} |", flush=True)


def bench_keypoints(quick):
    vi = json.loads((ICT / "vertex_indices.json").read_text())
    lm68 = np.array(vi["idx_to_landmark_verts"])
    print("\n### Key-point insertion on dense ICT sequences (26,719 points, 60 frames), errors in mm\n")
    print("Initial key points: the 68 landmark vertices. Table 1 form (initial / final) and Table 2 form "
          "(same number of random key points).\n")
    print("| performance | keys initial -> final | rounds | mean initial | mean final | RMSE initial | RMSE final "
          "| mean random | RMSE random | s per round |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for perf in (["talk"] if quick else list(PERFORMANCES)):
        frames, _ = dense_sequence(ICT, perf, 60, rng=0)
        t0 = time.perf_counter()
        ins = KeyPointInserter(rng=0).fit(frames, lm68)
        dt = time.perf_counter() - t0
        rounds = max(len(ins.history_) - 1, 1)
        init = sequence_errors(ins.deform(frames, lm68, frames[:, lm68]), frames, SKIN)
        fin = sequence_errors(ins.reconstruct(frames), frames, SKIN)
        n_new = len(ins.key_indices_) - len(lm68)
        rnd = [sequence_errors(ins.deform(frames, *random_insertion(frames, lm68, n_new, ins.radius_, rng=s)),
                               frames, SKIN) for s in range(3)] if n_new else [init]
        rm, rr = np.mean([r["mean"] for r in rnd]), np.mean([r["rmse"] for r in rnd])
        print(f"| {perf} | {len(lm68)} -> {len(ins.key_indices_)} | {len(ins.history_) - 1} | {init['mean'] * 10:.2f} "
              f"| {fin['mean'] * 10:.2f} | {init['rmse'] * 10:.2f} | {fin['rmse'] * 10:.2f} | {rm * 10:.2f} "
              f"| {rr * 10:.2f} | {dt / rounds:.1f} |", flush=True)


def bench_transfer(quick):
    vi = json.loads((ICT / "vertex_indices.json").read_text())
    lm68 = np.array(vi["idx_to_landmark_verts"])
    n_frames = 8 if quick else 20
    frames, _ = dense_sequence(ICT, "talk", n_frames, rng=0)
    targets = [("own neutral", frames[0])] + [(f"identity00{i}", read_obj_vertices(ICT / f"identity00{i}.obj"))
                                              for i in range(1 if quick else 4)]
    motion = np.linalg.norm(frames[1:, SKIN] - frames[:1, SKIN], axis=2) * 10
    print(f"\n### Facial transfer of ICT \"talk\" ({n_frames} frames, 26,719 points), face skin 0-9408, mm\n")
    print("Keys of eq. 6: the 68 landmark vertices (same index on the target); eqs. 7-9 with the defaults "
          "(6000 random target key points, seed 0). Truth: the same expression deltas added to the target. "
          f"Motion (= error of leaving the target still): mean {motion.mean():.2f}, p95 "
          f"{np.percentile(motion, 95):.2f}.\n")
    print("| target | mean error | p95 error | mean / motion mean | p95 / motion p95 | time s |")
    print("|---|---|---|---|---|---|")
    for name, tv in targets:
        t0 = time.perf_counter()
        out = transfer_sequence(frames, lm68, tv, lm68, rng=0)
        dt = time.perf_counter() - t0
        d = np.linalg.norm(out[1:, SKIN] - (tv[None] + frames[1:] - frames[0])[:, SKIN], axis=2) * 10
        print(f"| {name} | {d.mean():.2f} | {np.percentile(d, 95):.2f} | {d.mean() / motion.mean():.0%} "
              f"| {np.percentile(d, 95) / np.percentile(motion, 95):.0%} | {dt:.1f} |", flush=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", choices=("registration", "keypoints", "transfer"))
    a = ap.parse_args()
    if a.only in (None, "keypoints"):
        bench_keypoints(a.quick)
    if a.only in (None, "registration"):
        bench_registration(a.quick)
    if a.only in (None, "transfer"):
        bench_transfer(a.quick)
