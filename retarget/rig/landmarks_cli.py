"""``keyshape rig-check``: a rig with its landmarks drawn (neutral, blink, jaw open, smile), or a local page to
correct them (``-o LANDMARKS.json``, :mod:`keyshape.retarget.rig.landmark_edit`), and the landmark file found on a
rig with no correspondence, written beside a command's outputs for reuse and correction."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Callable

import numpy as np

from keyshape.retarget.rig.landmarks import PANELS, landmark_entries, panel_curves  # noqa: F401 (the sheet's)

#: each panel's side on the check sheet, pixels (``check_sheet(size=...)`` for another)
SHEET_PANEL = 420


def register(subparsers) -> None:
    """Add ``rig-check`` to ``subparsers``."""
    p = subparsers.add_parser(
        "rig-check", help="a picture of a rig with its landmarks drawn (neutral, blink, jaw open, smile), or a "
                          "page to correct them (-o FILE.json)",
        description="Draws the rig's scheme landmarks (lids, brows, pupils, lips) over the shaded rig in its "
                    "neutral and with its blinks, jawOpen and smiles at full weight, so a glance tells whether "
                    "they sit on the lids and the right lips. Without --landmarks, a rig that is not ICT-FaceKit "
                    "gets its landmarks found automatically, written beside the sheet (SHEET.landmarks.json) for "
                    "correction and reuse with --landmarks. With -o LANDMARKS.json, a page on 127.0.0.1 shows the "
                    "same panels instead: click a point, then where it should be (the nearest vertex, on the "
                    "point's own lip or lid); every change is saved to LANDMARKS.json.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("rig", nargs="+", metavar="DIR|FILE", help="rig: folder of shape OBJs (or a list of OBJ files)")
    p.add_argument("--neutral", default=None, help="the rig's neutral OBJ (default: the folder's neutral.*)")
    p.add_argument("--landmarks", default=None,
                   help="rig landmarks: a keyshape-rig-landmarks JSON or the rig's iBUG-68 vertex list (a JSON "
                        "list or one index a line); default: shipped for ICT-FaceKit, else found automatically")
    p.add_argument("-o", "--output", required=True,
                   help="SHEET.png (or .jpg); or LANDMARKS.json: serve a local web page to correct the landmarks "
                        "(click a point, then where it should be), every change saved to that file")
    p.set_defaults(func=run)


def landmarks_beside(output: str | Path) -> Path:
    """Where a command writing ``output`` writes the landmarks it found: ``OUTPUT_STEM.landmarks.json``."""
    out = Path(output)
    return out.with_name(f"{out.stem if out.suffix else out.name}.landmarks.json")


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
            from keyshape.retarget.rig.landmarks import contours48_on_rig, one_hot
            W68 = one_hot(read_landmark_list(landmarks), rig.n_vertices)
            for note in contours48_on_rig(W68, rig.neutral, rig.deltas, rig.names).notes:
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
    captions, C = panel_curves(rig)
    r = RigRenderer(rig, size=(size, size), landmarks=(W, scheme)).fit(C)
    return contact_sheet([r.render_curves(c) for c in C], captions, columns=len(C), tile_width=size)


def run(args) -> int:
    import cv2

    from keyshape.base.errors import InputError
    from keyshape.base.files import atomic_write
    from keyshape.base.schemes import load_scheme
    from keyshape.retarget.rig.model import load_rig, rig_landmarks

    edit = Path(args.output).suffix.lower() == ".json"
    if not edit and Path(args.output).suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise InputError("the output must be a sheet (.png or .jpg) or, to correct the landmarks in a local web "
                         "page, a landmarks file (.json)", args.output)
    scheme = load_scheme("contours48")
    rig = load_rig(args.rig, args.neutral)
    if edit and (rig.mesh is None or not rig.mesh.polygons):
        raise InputError("the rig's neutral has no faces to show", rig.neutral_file)
    if edit and args.landmarks is not None:             # a file the geometry refutes is what the page corrects
        from keyshape.retarget.rig.landmarks import landmark_problem
        W, _ = rig_landmarks(rig, scheme.name, args.landmarks, check=False)
        problem = landmark_problem(W @ rig.neutral, scheme, rig.neutral.mean(axis=0))
        if problem:
            print(f"keyshape: {args.landmarks}: these landmarks do not fit the rig ({problem}): correct them in the page")
    else:
        landmarks = resolve_landmarks(rig, scheme.name, args.landmarks, None if edit else args.output)
        W, _ = rig_landmarks(rig, scheme.name, landmarks)
    if edit:
        from keyshape.base.formats.poses import write_rig_landmarks
        from keyshape.retarget.rig.landmark_edit import serve
        write_rig_landmarks(args.output, scheme.name, rig.n_vertices, landmark_entries(W))
        serve(args.output, rig, W, scheme)
        return 0
    img = check_sheet(rig, W, scheme, SHEET_PANEL)
    ok, buf = cv2.imencode(Path(args.output).suffix.lower(), img)
    with atomic_write(args.output, "wb") as f:
        f.write(buf.tobytes())
    print(f"keyshape rig-check: {rig.n_vertices} vertices, {rig.n_shapes} shapes -> {args.output}")
    return 0
