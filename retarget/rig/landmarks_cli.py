"""``keyshape rig-check``: a rig with its landmarks drawn (neutral, blink, jaw open, smile), and the landmark
file found on a rig with no correspondence, written beside a command's outputs for reuse and correction."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Callable

import numpy as np

#: each panel's side on the check sheet, pixels (``check_sheet(size=...)`` for another)
SHEET_PANEL = 420
#: the panels of the check sheet: caption, {shape name key: weight}
PANELS = (("neutral", {}), ("blink", {"eyeblinkleft": 1.0, "eyeblinkright": 1.0}), ("jaw open", {"jawopen": 1.0}),
          ("smile", {"mouthsmileleft": 1.0, "mouthsmileright": 1.0}))


def register(subparsers) -> None:
    """Add ``rig-check`` to ``subparsers``."""
    p = subparsers.add_parser(
        "rig-check", help="a picture of a rig with its landmarks drawn (neutral, blink, jaw open, smile)",
        description="Draws the rig's scheme landmarks (lids, brows, pupils, lips) over the shaded rig in its "
                    "neutral and with its blinks, jawOpen and smiles at full weight, so a glance tells whether "
                    "they sit on the lids and the right lips. Without --landmarks, a rig that is not ICT-FaceKit "
                    "gets its landmarks found automatically, written beside the sheet (SHEET.landmarks.json) for "
                    "correction and reuse with --landmarks.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("rig", nargs="+", metavar="DIR|FILE", help="rig: folder of shape OBJs (or a list of OBJ files)")
    p.add_argument("--neutral", default=None, help="the rig's neutral OBJ (default: the folder's neutral.*)")
    p.add_argument("--landmarks", default=None,
                   help="rig landmarks: a keyshape-rig-landmarks JSON or the rig's iBUG-68 vertex list (a JSON "
                        "list or one index a line); default: shipped for ICT-FaceKit, else found automatically")
    p.add_argument("-o", "--output", required=True, help="SHEET.png (or .jpg)")
    p.set_defaults(func=run)


def landmarks_beside(output: str | Path) -> Path:
    """Where a command writing ``output`` writes the landmarks it found: ``OUTPUT_STEM.landmarks.json``."""
    out = Path(output)
    return out.with_name(f"{out.stem if out.suffix else out.name}.landmarks.json")


def landmark_entries(W: np.ndarray) -> list:
    """A weight matrix's rows as landmark-file entries: a vertex index, or ``[[vertex, weight], ...]``."""
    out = []
    for row in np.asarray(W, np.float64):
        nz = np.flatnonzero(np.abs(row) > 1e-12)
        if len(nz) == 1:
            out.append(int(nz[0]))
        else:
            w = row[nz] / row[nz].sum()
            out.append([[int(v), float(x)] for v, x in zip(nz, w)])
    return out


def resolve_landmarks(rig, scheme: str, landmarks: str | Path | None, output: str | Path | None,
                      say: Callable[[str], None] = print) -> str | Path | None:
    """The landmark file a command uses on ``rig``: ``landmarks`` as given, or the shipped one, or, for a rig
    with neither, the landmarks found on it (:func:`keyshape.retarget.rig.model.found_landmarks`), written
    beside ``output`` (:func:`landmarks_beside`) and said in one line. What the landmarks imply for the
    gaze (a rig without eyeballs) is said in one more line.

    Raises :class:`~keyshape.base.errors.InputError` (one line, naming the file) for a file that is wrong.
    """
    from keyshape.base.formats.poses import read_landmark_list, write_rig_landmarks
    from keyshape.retarget.rig.model import default_landmarks, found_landmarks, rig_landmarks
    if landmarks is not None:
        rig_landmarks(rig, scheme, landmarks)                       # refused here, before the work
        if read_landmark_list(landmarks) is not None and scheme == "contours48":
            from keyshape.retarget.rig.landmarks import contours48_from_ibug68, eye_width, one_hot, still_vertices
            W68 = one_hot(read_landmark_list(landmarks), rig.n_vertices)
            for note in contours48_from_ibug68(W68, rig.neutral, still_vertices(
                    rig.deltas, rig.names, eye_width(W68, rig.neutral))).notes:
                say(f"keyshape: {note}")
        return landmarks
    if default_landmarks(rig.n_vertices, scheme) is not None:
        return None
    found = found_landmarks(rig, scheme)
    path = landmarks_beside(output) if output is not None else None
    if path is not None:
        write_rig_landmarks(path, scheme, rig.n_vertices, landmark_entries(found.W))
    where = f" -> {path} (correct it if need be, and give it with --landmarks)" if path else ""
    say(f"keyshape: no landmark correspondence for this rig ({rig.n_vertices} vertices): found one from its own "
        f"shapes (blinks, jawOpen, brows) by fitting ICT-FaceKit's face onto it{where}")
    for note in found.notes:
        say(f"keyshape: {note}")
    return path


def check_sheet(rig, W: np.ndarray, scheme, size: int = SHEET_PANEL) -> np.ndarray:
    """The check sheet (BGR): the rig in each of :data:`PANELS` that it has the shapes for, its landmarks drawn."""
    from keyshape.base.draw import contact_sheet
    from keyshape.retarget.output.preview import RigRenderer
    from keyshape.retarget.targets.target_set import name_key
    keys = [name_key(n) for n in rig.names]
    rows, captions = [], []
    for caption, mix in PANELS:
        c = np.zeros(rig.n_shapes)
        for k, w in mix.items():
            c[[j for j, x in enumerate(keys) if x == k]] = w
        if mix and not c.any():
            continue
        rows.append(c)
        captions.append(caption)
    C = np.stack(rows)
    r = RigRenderer(rig, size=(size, size), landmarks=(W, scheme)).fit(C)
    return contact_sheet([r.render_curves(c) for c in C], captions, columns=len(C), tile_width=size)


def run(args) -> int:
    import cv2

    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_write, check_output
    from keyshape.base.schemes import load_scheme
    from keyshape.retarget.rig.model import load_rig, rig_landmarks

    if Path(args.output).suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise InputError("the sheet must be a .png or .jpg", args.output)
    inputs = [args.neutral, args.landmarks]
    check_output(args.output, "file", inputs)
    scheme = load_scheme("contours48")
    rig = load_rig(args.rig if len(args.rig) > 1 else args.rig[0], args.neutral)
    landmarks = resolve_landmarks(rig, scheme.name, args.landmarks, args.output)
    W, _ = rig_landmarks(rig, scheme.name, landmarks)
    img = check_sheet(rig, W, scheme, SHEET_PANEL)
    ok, buf = cv2.imencode(Path(args.output).suffix.lower(), img)
    with atomic_write(args.output, "wb") as f:
        f.write(buf.tobytes())
    print(f"keyshape rig-check: {rig.n_vertices} vertices, {rig.n_shapes} shapes -> {args.output}")
    return 0
