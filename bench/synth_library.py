"""A synthetic footage library for ``keyshape batch`` (bench/bench_batch.py and the batch tests): actors x takes of
``keyshape synth video`` footage.

Each actor is one synthetic person (``keyshape synth video`` with the actor's own seed: the seed
sets the face and the look as well as the performance); the actor's footage (``footage/video.mp4``
with its suggested ``labels/``) is cut into takes of ``frames`` frames (re-encoded, so each take
is a video file of its own). Actors get simple target key shapes (a grid mesh per key, see
:func:`grid_targets`) so that retargeting runs too.
"""
from __future__ import annotations

import contextlib
import json
from pathlib import Path

import numpy as np

from keyshape.base.formats.obj import Mesh, write_obj


def grid_targets(folder: str | Path, keys: dict[str, int], seed: int = 0, n: int = 6) -> dict[str, list[int]]:
    """Write ``neutral.obj`` (an ``n`` x ``n`` vertex grid of quads) and one randomly displaced copy per key
    (``mouth_0.obj`` ...) into ``folder``; return the regions (lower half: mouth, upper half: eyes)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    xy = np.stack(np.meshgrid(np.arange(n), np.arange(n)), -1).reshape(-1, 2).astype(float)
    verts = np.column_stack([xy, np.zeros(len(xy))])
    quads = [np.array([r * n + c, r * n + c + 1, (r + 1) * n + c + 1, (r + 1) * n + c])
             for r in range(n - 1) for c in range(n - 1)]
    mesh = Mesh(verts, quads)
    write_obj(folder / "neutral.obj", mesh)
    for region, k in keys.items():
        for i in range(k):
            write_obj(folder / f"{region}_{i}.obj", mesh, verts + rng.normal(0, 0.2, verts.shape))
    return {"mouth": np.flatnonzero(xy[:, 1] < n / 2).tolist(), "eyes": np.flatnonzero(xy[:, 1] >= n / 2).tolist()}


def synth_library(folder: str | Path, actors: int = 2, takes: int = 2, frames: int = 60, seed: int = 0,
                  keys: int = 4, morphs: int = 120, labels: int = 12, size=(640, 480)) -> Path:
    """Write ``actors`` x ``takes`` synthetic takes of ``frames`` frames and a ``manifest.toml``; return its path.

    Actor ``a`` has seed ``seed + a``; ``size`` is the frame size (width, height). Existing videos are kept (a benchmark can reuse the library).
    """
    from keyshape.base.formats.video import VideoReader, video_writer
    from keyshape.data_synth.video import synthesize

    folder = Path(folder)
    lines = ["[settings]", 'outputs = ["tracks", "weights", "glb", "curves"]', ""]
    take_lines = []
    for a in range(actors):
        name = f"actor{a}"
        foot = folder / name / "footage"
        if not (foot / "video.mp4").is_file():
            synthesize(foot, frames=frames * takes, seed=seed + a, size=size, labels=labels)
        paths = [folder / name / f"take{t:02d}.mp4" for t in range(takes)]
        if not all(p.is_file() for p in paths):
            reader = VideoReader(foot / "video.mp4")
            size = (reader.info.width, reader.info.height)
            with contextlib.ExitStack() as stack:
                outs = [stack.enter_context(video_writer(p, reader.info.fps, size)) for p in paths]
                for i, img in reader:
                    outs[min(i // frames, takes - 1)].write(img)
        for t in range(takes):
            take_lines += ["[[takes]]", f'actor = "{name}"', f'video = "{name}/take{t:02d}.mp4"', ""]
        lines += [f"[actors.{name}]", f'video = "{name}/footage/video.mp4"', f'labels = "{name}/footage/labels"',
                  f"keys = {keys}", f"morphs = {morphs}", 'regions = ["mouth", "eyes"]']
        regions = grid_targets(folder / name / "targets", {"mouth": keys, "eyes": keys}, seed=a)
        (folder / name / "regions.json").write_text(json.dumps(regions))
        lines += [f'targets = "{name}/targets"', f'target_regions = "{name}/regions.json"']
        lines.append("")
    manifest = folder / "manifest.toml"
    manifest.write_text("\n".join(lines + take_lines))
    return manifest
