"""A small label folder for the server and browser tests."""
from __future__ import annotations

import json

import numpy as np

from keyshape.base.formats.labels import write_pts
from keyshape.tracker.labelling.prepare import template_points
from keyshape.base.schemes import load_scheme


def make_folder(root, frames=(5, 40)):
    import cv2
    folder = root / "labels"
    (folder / "frames").mkdir(parents=True)
    sch = load_scheme("contours48")
    for f in frames:
        cv2.imwrite(str(folder / "frames" / f"{f:06d}.png"), np.full((120, 160, 3), 90, np.uint8))
        write_pts(folder / f"{f:06d}.pts", template_points(sch, 160, 120))
    (folder / "session.json").write_text(json.dumps({"scheme": "contours48", "video": "v.mp4",
                                                     "frames": list(frames)}))
    return folder
