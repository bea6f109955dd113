"""Issue 14 acceptance: a synthetic take onto the full ICT-FaceKit rig through the default chain.

``keyshape synth video`` (600 frames, seed 11: no test uses it), then with default
settings ``train``, ``track``, ``select -k 8 --region mouth --region eyes``, ``decompose``,
``pose`` (no hand correction) and ``retarget --poses ... -o curves.csv``; the recovered
ARKit curves are compared with truth.json's hidden components (Pearson r per component;
targets r >= 0.9 for jawOpen and both blinks, mean >= 0.8) and the rig driven by the
recovered curves with the rig driven by the hidden weights (mean face-skin vertex error,
target <= 0.65 x the hidden motion). Diagnostic rows: the same from the exact contours
(truth.csv instead of the tracks), the best linear map from key weights (an upper bound), and
"oracle poses": the same key weights with each key's pose set to the hidden weights at its frame
(relative to the neutral frame's), which separates what the pose fit loses from what the keys
and their weights lose; "exact key shapes": the same keys and weights with each key's shape (and the
neutral's) taken from the exact contours at its frame and posed by ``pose``'s fit, which separates what
tracking errors at the key frames cost (seed 12: 0.686 tracked, 0.544 with exact key shapes; its widest
jaw openings are tracked with the lower lip on the teeth, frames 96-110). Where the error comes from:
each component's gain (slope of the recovered curve on the hidden weight: < 1 under-driven), the
gain a 2D fit of exactly the right rig shape would give (``component_gains``: the synthetic face's
motion against the rig shape's projected motion; an amplitude difference between the two faces that
no 2D fit can see), the error with the oracle poses scaled by those gains (the floor of a perfect 2D
pose fit), and the error with only the mouth's or only the eyes' shapes fitted (the other region's
from the oracle poses).

    python bench/rig_accuracy.py [--seed 11] [--work DIR] [--rig ../shared/data/ict-facekit]
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
TARGETS = {"jawOpen": 0.9, "eyeBlink_L": 0.9, "eyeBlink_R": 0.9}


def run_chain(work: Path, seed: int, rig: Path, frames: int = 600, tracks: Path | None = None) -> dict:
    """Run the default chain in ``work`` (re-using finished steps); returns the paths."""
    from keyshape.cli import main
    work.mkdir(parents=True, exist_ok=True)
    syn = work / "take"
    if not (syn / "truth.json").is_file():
        assert main(["synth", "video", str(syn), "--frames", str(frames), "--seed", str(seed)]) == 0
    if tracks is None:
        tracks = work / "tracks.csv"
        if not tracks.is_file():
            assert main(["train", str(syn / "video.mp4"), "--labels", str(syn / "labels"),
                         "-o", str(work / "model.npz")]) == 0
            assert main(["track", str(syn / "video.mp4"), "--model", str(work / "model.npz"),
                         "-o", str(tracks)]) == 0
    tag = tracks.stem
    p = {k: work / f"{tag}_{k}" for k in ("keys.json", "weights.csv", "poses.json", "curves.csv")}
    # the synthetic face is a 2D drawing whose head only moves in the image plane: the 3D head step
    # (select's default) reads its expressions as head turns (mouthFunnel r 0.27 on seed 11), so its
    # takes are stabilised in 2D on the eye corners, as they were measured before the 3D head
    assert main(["select", str(tracks), "-k", "8", "--region", "mouth", "--region", "eyes",
                 "--head-pose", "rigid", "-o", str(p["keys.json"])]) == 0
    assert main(["decompose", str(tracks), "--keys", str(p["keys.json"]), "-o", str(p["weights.csv"])]) == 0
    assert main(["pose", str(p["keys.json"]), "--rig", str(rig), "-o", str(p["poses.json"])]) == 0
    assert main(["retarget", str(p["weights.csv"]), "--poses", str(p["poses.json"]), "--rig", str(rig),
                 "-o", str(p["curves.csv"])]) == 0
    p["truth.json"] = syn / "truth.json"
    return p


def score(paths: dict, rig) -> dict:
    from keyshape.base.formats.weights import read_weights
    from rig_truth import component_columns, score_curves
    from keyshape.retarget.rig.model import ICT_FACE_SKIN
    truth = json.loads(Path(paths["truth.json"]).read_text())
    hidden = np.asarray(truth["weights"])
    _, names, curves, _ = read_weights(paths["curves.csv"])
    order = [names.index(n) for n in rig.names]
    s = score_curves(rig, curves[:, order], truth["components"], hidden, np.arange(ICT_FACE_SKIN))
    fitted = curves[:, order]
    _, cols, w, _ = read_weights(paths["weights.csv"])
    oracle = oracle_curves(paths, rig, cols, w, truth["components"], hidden)
    s["oracle"] = score_curves(rig, oracle, truth["components"], hidden, np.arange(ICT_FACE_SKIN))
    s["gain"] = {c: float(np.polyfit(hidden[:, i], fitted[:, component_columns(rig.names, c)].mean(axis=1), 1)[0])
                 for i, c in enumerate(truth["components"])}
    gains, cos = geometric_gains(truth, rig)
    s["geometric_gain"] = dict(zip(truth["components"], gains.tolist()))
    s["geometric_cos"] = dict(zip(truth["components"], cos.tolist()))
    s["geometric_floor"] = score_curves(rig, oracle_curves(paths, rig, cols, w, truth["components"], hidden * gains),
                                        truth["components"], hidden, np.arange(ICT_FACE_SKIN))
    lib = json.loads(Path(paths["poses.json"]).read_text())["regions"]
    for region in ("mouth", "eyes"):
        cols_r = [rig.names.index(n) for n in lib.get(region, {}).get("shapes", [])]
        mix = oracle.copy()
        mix[:, cols_r] = fitted[:, cols_r]
        s[f"only_{region}_fitted"] = score_curves(rig, mix, truth["components"], hidden,
                                                  np.arange(ICT_FACE_SKIN))["error_ratio"]
    s["exact_keys"] = score_curves(rig, exact_key_curves(paths, rig, cols, w), truth["components"], hidden,
                                   np.arange(ICT_FACE_SKIN))["error_ratio"]
    X = np.column_stack([w, np.ones(len(w))])
    s["linear_bound"] = {c: float(np.corrcoef(X @ np.linalg.lstsq(X, hidden[:, i], rcond=None)[0],
                                              hidden[:, i])[0, 1]) for i, c in enumerate(truth["components"])}
    return s


def geometric_gains(truth: dict, rig) -> tuple[np.ndarray, np.ndarray]:
    """Per hidden component: the weight of its rig shape(s) that best makes its 2D motion, and the cosine."""
    from rig_truth import component_gains
    from keyshape.retarget.rig.model import project, rig_landmarks
    W, _ = rig_landmarks(rig, truth["scheme"])
    return component_gains(truth["neutral"], truth["basis"], truth["components"], rig.names, project(W @ rig.neutral),
                           project(np.einsum("pv,svc->spc", W, rig.deltas, optimize=True)))


def exact_key_curves(paths: dict, rig, cols, w) -> np.ndarray:
    """Rig curves from the same keys and key weights with each key's (and the neutral's) shape taken from
    the exact contours (truth.csv) at its frame and posed by ``keyshape pose``'s fit: what tracking errors
    at the key frames cost the pose fit."""
    import copy
    from keyshape.base.formats.keys import read_keys, read_keys_head_pose
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.schemes import load_scheme
    from keyshape.decompose.regions import head_shapes
    from keyshape.retarget.api import fit_poses
    from keyshape.retarget.rig.poses import curves_from_library
    scheme, _, regions = read_keys(paths["keys.json"])
    exact = Path(paths["truth.json"]).with_name("truth.csv")
    shapes, _ = head_shapes(read_tracks(exact), load_scheme(scheme), "rigid", exact)
    regions = [copy.copy(rk) for rk in regions]
    for rk in regions:
        rk.keys = shapes[np.asarray(rk.frames)][:, rk.points]
        rk.rest = rk.neutral = shapes[int(rk.rest_frame), rk.points]
    lib, _ = fit_poses(regions, scheme, rig, read_keys_head_pose(paths["keys.json"]))
    return curves_from_library(w, cols, lib, rig.names)


def oracle_curves(paths: dict, rig, cols, w, components, hidden) -> np.ndarray:
    """Rig curves from the key weights with oracle poses: each key's pose is the hidden weights at
    its frame minus those at the region's neutral frame, on the region's shapes (POSES.json)."""
    from rig_truth import truth_curves

    from keyshape.base.formats.keys import read_keys
    _, _, regions = read_keys(paths["keys.json"])
    lib = json.loads(Path(paths["poses.json"]).read_text())["regions"]
    out = np.zeros((len(w), rig.n_shapes))
    for rk in regions:
        shapes = [rig.names.index(n) for n in lib[rk.region]["shapes"]]
        P = truth_curves(rig.names, components, hidden[np.asarray(rk.frames)])[:, shapes]
        pr = truth_curves(rig.names, components, hidden[[int(rk.rest_frame)]])[0, shapes]
        out[:, shapes] += pr + w[:, [cols.index(n) for n in rk.names]] @ (P - pr)
    return np.clip(out, 0.0, 1.0)


def table(rows: dict[str, dict]) -> str:
    comps = list(next(iter(rows.values()))["r"])
    out = [f"{'component':16s}" + "".join(f"{k:>22s}" for k in rows)]
    for c in comps:
        out.append(f"{c:16s}" + "".join(f"{v['r'][c]:>10.3f} (lin {v['linear_bound'][c]:5.3f})" for v in rows.values()))
    out.append(f"{'mean r':16s}" + "".join(f"{v['mean_r']:>10.3f} (lin {np.mean(list(v['linear_bound'].values())):5.3f})"
                                           for v in rows.values()))
    out.append(f"{'err / motion':16s}" + "".join(f"{v['error_ratio']:>10.3f}".ljust(22) for v in rows.values()))
    out.append(f"{'oracle poses':16s}" + "".join(f"{v['oracle']['mean_r']:>10.3f} r, {v['oracle']['error_ratio']:.3f} err".ljust(22)
                                                 for v in rows.values()))
    out.append(f"{'  err, motion cm':16s}" + "".join(f"{v['vertex_error']:>10.3f}, {v['hidden_motion']:.3f}".ljust(22)
                                                     for v in rows.values()))
    out.append(f"{'exact key shapes':16s}" + "".join(f"{v['exact_keys']:>10.3f} err".ljust(22) for v in rows.values()))
    out.append(f"{'geometric floor':16s}" + "".join(f"{v['geometric_floor']['error_ratio']:>10.3f} err".ljust(22)
                                                    for v in rows.values()))
    for region in ("mouth", "eyes"):
        out.append(f"{'only ' + region + ' fit':16s}"
                   + "".join(f"{v[f'only_{region}_fitted']:>10.3f} err".ljust(22) for v in rows.values()))
    first = next(iter(rows.values()))
    out.append("")
    out.append(f"{'gain (slope)':16s}" + "".join(f"{k:>22s}" for k in rows) + "   geometric gain (cos)")
    for c in comps:
        out.append(f"{c:16s}" + "".join(f"{v['gain'][c]:>22.2f}" for v in rows.values())
                   + f"   {first['geometric_gain'][c]:8.2f} ({first['geometric_cos'][c]:.2f})")
    return "\n".join(out)


def verdict(s: dict) -> list[str]:
    out = [f"{c}: r {s['r'][c]:.3f} {'>=' if s['r'][c] >= t else '<'} {t} "
           f"({'met' if s['r'][c] >= t else 'NOT met'})" for c, t in TARGETS.items()]
    out.append(f"mean r {s['mean_r']:.3f} ({'met' if s['mean_r'] >= 0.8 else 'NOT met'}: >= 0.8)")
    out.append(f"vertex error / hidden motion {s['error_ratio']:.3f} "
               f"({'met' if s['error_ratio'] <= 0.65 else 'NOT met'}: <= 0.65)")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--work", default=None, help="work folder (kept; default a temporary one)")
    ap.add_argument("--rig", default=str(REPO.parent / "shared" / "data" / "ict-facekit"))
    a = ap.parse_args()
    from keyshape.retarget.rig.model import load_rig
    rig = load_rig(a.rig, with_mesh=False)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(a.work or tmp)
        tracked = run_chain(work, a.seed, Path(a.rig))
        exact = run_chain(work, a.seed, Path(a.rig), tracks=work / "take" / "truth.csv")
        rows = {"tracked (default)": score(tracked, rig), "exact contours": score(exact, rig)}
    print(f"seed {a.seed}, 600 frames, ICT-FaceKit rig ({rig.n_shapes} shapes); r = Pearson of the recovered "
          "curve with the hidden weight (lin = best linear map from the key weights, a bound)")
    print(table(rows))
    print("targets (tracked, default chain):")
    for line in verdict(rows["tracked (default)"]):
        print("  " + line)


if __name__ == "__main__":
    main()
