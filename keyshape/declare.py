"""What every command reads and writes: the declaration the output rule checks before any work.

Design notes and figures: docs/reliability.md, "Notes on the code", ``keyshape/declare.py``.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Callable, Iterable

from keyshape.base.errors import InputError

_TEXT = "text"

#: command -> argument dest -> role; a dest absent from a command's entry is an error in the test
ROLES: dict[str, dict[str, str]] = {
    "demo": {"out_dir": "folder"},
    "synth video": {"out_dir": "folder", "size": _TEXT, "preview": "file"},
    "synth mocap": {"out_dir": "folder", "facekit": "in"},
    "synth face3d": {"out_dir": "folder", "rig": "in", "size": _TEXT, "preview": "file"},
    "label": {"video": "in", "out": "folder", "scheme": _TEXT, "tracks": "in"},
    "scheme": {"name": _TEXT},
    "train": {"video": "in", "labels": "in", "scheme": _TEXT, "output": "file"},
    "track": {"video": "in", "model": "in", "output": "file", "overlay": "file", "smooth": _TEXT},
    "select": {"tracks": "in", "method": _TEXT, "neutral_frame": _TEXT, "region": _TEXT, "scheme": _TEXT,
               "head_pose": _TEXT, "output": "file", "sheet": "file", "video": "in"},
    "decompose": {"tracks": "in", "keys": "in", "solver": _TEXT, "output": "file"},
    "compare": {"tracks": "in", "methods": _TEXT, "region": _TEXT, "output": "folder"},
    "pose": {"keys": "in", "rig": "in", "neutral": "in", "landmarks": "in", "output": "file"},
    # POSES.json is the file the page edits on the user's request (keyshape.base.files.user_save)
    "pose-edit": {"poses": "in", "rig": "in", "neutral": "in", "keys": "in"},
    "solve": {"tracks": "in", "keys": "in", "rig": "in", "neutral": "in", "landmarks": "in", "poses": "in",
              "weights": "in", "gaze": _TEXT, "output": "file"},
    "retarget": {"weights": "in", "targets": "in", "poses": "in", "rig": "in", "neutral": "in", "regions": "in",
                 "tracks": "in", "gaze": _TEXT, "landmarks": "in", "output": "file|folder"},
    "preview": {"video": "in", "tracks": "in", "curves": "in", "rig": "in", "neutral": "in", "frames": _TEXT,
                "sheet": "file", "landmarks": "in", "compare": "in", "contours": _TEXT, "output": "file"},
    "live": {"source": "in", "model": "in", "keys": "in", "poses": "in", "rig": "in", "landmarks": "in",
             "host": _TEXT, "subject": _TEXT, "osc": _TEXT, "calibration": "in", "gaze": _TEXT},
    "mocap": {"markers": "in", "target": "in", "target_markers": "in", "rigid": _TEXT, "masks": "in",
              "method": _TEXT, "duplicate_labels": _TEXT, "up": _TEXT, "output": "file|folder"},
    "register": {"reference": "in", "target": "in", "landmarks": "in", "output": "file", "markers": "in",
                 "out_markers": "file", "masks": "in", "out_masks": "file"},
    "keypoints": {"sequence": "in", "initial": "in", "output": "file"},
    "transfer": {"sequence": "in", "target": "in", "keypoints": "in", "landmarks": "in", "output": "file"},
    "batch": {"manifest": "in", "output": "folder", "scheduler": _TEXT},
    "animate": {"video": "in", "rig": "in", "output": "file", "livelink": "file", "preview": "file", "labels": "in",
                "landmarks": "in", "work": "folder", "example": "folder"},
    # -o LANDMARKS.json: written once under the rule, then rewritten by the correction page on the user's
    # request (keyshape.base.files.user_save), as pose-edit's POSES.json
    "rig-check": {"rig": "in", "neutral": "in", "landmarks": "in", "output": "file"},
}


def _track_sidecars(args) -> list[Path]:
    from keyshape.base.formats.tracks import meta_path
    return [meta_path(args.output)] if args.output else []


def _label_files(args) -> list[Path]:
    out = Path(args.out)
    return [out / "session.json", out / "contact_sheet.png", out / "footage.json"]


#: command -> the further files it writes beside its declared outputs (sidecars), same rule
SIDECARS: dict[str, Callable[[argparse.Namespace], Iterable[Path]]] = {
    "track": _track_sidecars,
    "label": _label_files,
}

#: commands whose output folder is governed by their own content-hash record (batch.json), checked
#: before work by the command itself (keyshape.batch.check_layout)
OWN_RECORD = {"batch"}


def _values(v) -> list[str]:
    if v is None:
        return []
    if isinstance(v, (list, tuple)):
        return [str(x) for x in v if x is not None]
    return [str(v)]


def _is_folder_output(path: Path) -> bool:
    return path.suffix == "" or (path.is_dir() and not path.is_symlink())


def declared(command: str, args: argparse.Namespace) -> tuple[list[Path], list[Path], list[Path]]:
    """(inputs, output files, output folders) that ``args`` of ``command`` name."""
    roles = ROLES.get(command, {})
    named: dict[str, list[Path]] = {"in": [], "file": [], "folder": []}
    for dest, role in roles.items():
        for v in map(Path, _values(getattr(args, dest, None))):
            kind = ("folder" if _is_folder_output(v) else "file") if role == "file|folder" else role
            if kind in named:                   # not a text option
                named[kind].append(v)
    inputs, files, folders = named["in"], named["file"], named["folder"]
    if command in SIDECARS and all(getattr(args, d, None) is not None for d, r in roles.items()
                                   if r in ("file", "folder") and d in ("output", "out")):
        files += list(SIDECARS[command](args))
    return inputs, files, folders


def check_declared(command: str, args: argparse.Namespace):
    """Check every declared output of ``args`` against the output rule before any work; return the
    :class:`~keyshape.base.files.Run` to run the command under."""
    from keyshape.base.files import Run, _same_file, check_output, run_rules

    inputs, files, folders = declared(command, args)
    run = Run(inputs, overwrite=bool(getattr(args, "overwrite", False)), can_overwrite=True, command=command)
    with run_rules(run):
        for d in folders:
            if d.is_symlink():
                raise InputError("is a symbolic link; keyshape never writes through a link: choose another "
                                 "output folder", d)
            for inp in inputs:
                if (d.exists() or inp.exists()) and _same_file(d, inp):
                    raise InputError(f"the output folder is an input folder ({inp}); choose another folder", d)
            check_output(d, "folder")
        seen: list[Path] = []
        for f in files:
            if f.is_dir() and not f.is_symlink():
                raise InputError("is a folder; the output must be a file name", f)
            check_output(f, "file")          # writable folder, a file name, and the rule (guard_file)
            for s in seen:
                if f == s or _same_file(f, s) and f.exists():
                    raise InputError("named twice as an output", f)
            seen.append(f)
    return None if command in OWN_RECORD else run
