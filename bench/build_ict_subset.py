"""Regenerate ``retarget/data/ict_face.npz``: the small ICT-FaceKit subset the demo ships.

Usage (from the repository root)::

    PYTHONPATH=. python bench/build_ict_subset.py [--source ../shared/data/ict-facekit] [--out retarget/data/ict_face.npz]

Keeps the face skin only (vertices 0-9408 of ``generic_neutral_mesh.obj``, the
polygons made only of them, fan-triangulated), the neutral positions and the
delta ``expression - neutral`` of every ICT-FaceKit expression, stored as float16
centimetres (resolution under 0.01 mm at these magnitudes) in a compressed npz,
plus the MIT licence text beside it (``LICENSE-ICT-FaceKit.txt``).
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

FACE_SKIN = 9409   # vertices 0..9408 are the face skin (see ../shared/data/README.md)
REPO = Path(__file__).resolve().parents[1]


def build(source: Path, out: Path) -> Path:
    from keyshape.base.errors import require_dir
    from keyshape.base.files import atomic_path
    from keyshape.base.formats.obj import read_obj, read_obj_vertices

    source = require_dir(source, "ICT-FaceKit folder")
    mesh = read_obj(source / "generic_neutral_mesh.obj", require_faces=True)
    names = json.loads((source / "vertex_indices.json").read_text())["expressions"]
    tri = mesh.triangles
    tri = tri[(tri < FACE_SKIN).all(axis=1)]
    neutral = mesh.vertices[:FACE_SKIN]
    deltas = np.stack([read_obj_vertices(source / f"{n}.obj", mesh.n_vertices)[:FACE_SKIN] - neutral
                       for n in names])
    landmarks = np.asarray(json.loads((source / "vertex_indices.json").read_text())["idx_to_landmark_verts"])
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, neutral=neutral.astype(np.float32), triangles=tri.astype(np.int32),
                                names=np.array(names), deltas=deltas.astype(np.float16),
                                landmarks=landmarks.astype(np.int32))
    out.chmod(0o644)
    shutil.copyfile(source / "LICENSE", out.parent / "LICENSE-ICT-FaceKit.txt")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=str(REPO.parent / "shared" / "data" / "ict-facekit"))
    ap.add_argument("--out", default=str(REPO / "retarget" / "data" / "ict_face.npz"))
    a = ap.parse_args()
    p = build(Path(a.source), Path(a.out))
    print(f"wrote {p} ({p.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
