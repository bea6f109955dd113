"""The key-frame sheet: every chosen key frame cropped from the video with its contours, numbered.

This is what the artist models the target key shapes from, so each tile shows
the face enlarged, the key's region drawn bold in the scheme's colours over the
rest of the face drawn thin and grey, and the key's name (``mouth_3``), frame
number and distance from the actor's neutral (``d``: RMS point distance in model
units) in a caption. Each region starts with its neutral frame (tile ``N``).
"""
from __future__ import annotations

import cv2
import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.draw import contact_sheet, crop_around, draw_shape
from keyshape.base.formats.tracks import Tracks
from keyshape.base.schemes import Scheme
from keyshape.decompose.regions import RegionKeys, to_image


def key_tiles(frames_bgr: dict, tracks: Tracks, scheme: Scheme, regions: list[RegionKeys],
              tile_width: int = 280, poses: np.ndarray | None = None) -> tuple[list[np.ndarray], list[str]]:
    """One annotated tile per key shape; ``frames_bgr`` maps frame number -> BGR image.

    ``poses``: (n_frames, 2, 3) ``image_from_head`` the keys' head frame goes with
    (:func:`~keyshape.decompose.regions.stable_pose`; default the tracks' own pose)."""
    poses = tracks.pose if poses is None else poses
    row_of = {int(f): i for i, f in enumerate(tracks.frame)}
    tiles, captions = [], []
    for rk in regions:
        sub = Scheme(scheme.name, scheme.n_points,
                     {n: c for n, c in scheme.contours.items() if set(c) <= set(rk.points.tolist())},
                     scheme.closed, scheme.regions, scheme.inter_ocular)
        ref = rk.rest if rk.rest is not None else rk.neutral
        items = list(zip(rk.names, rk.frames, rk.keys, rk.from_frame))
        if rk.rest is not None and rk.rest_frame is not None:          # the actor's neutral first
            items.insert(0, (f"{rk.region}_neutral", rk.rest_frame, rk.rest, True))
        for name, f, key, exact in items:
            if int(f) not in row_of:
                raise InputError(f"key {name} names frame {f}, which the tracks file does not have")
            r = row_of[int(f)]
            face = tracks.points[r]
            shape = face.copy()
            shape[rk.points] = to_image(key[None], poses[r:r + 1])[0]   # the key itself, in the image
            crop, p = crop_around(frames_bgr[int(f)], face, margin=0.3)
            s = tile_width / max(crop.shape[1], 1)
            big = cv2.resize(crop, (tile_width, max(1, int(round(crop.shape[0] * s)))), interpolation=cv2.INTER_CUBIC)
            p = p * s
            big = draw_shape(big, p, scheme, colour=(150, 150, 150), thickness=1)
            big = draw_shape(big, np.where(np.isin(np.arange(len(p)), rk.points)[:, None], p, np.nan), sub,
                             thickness=2)
            num = name.rsplit("_", 1)[1][:1].upper() if name.endswith("neutral") else name.rsplit("_", 1)[1]
            cv2.putText(big, num, (8, big.shape[0] - 10), cv2.FONT_HERSHEY_DUPLEX, 1.2, (0, 0, 0), 4, cv2.LINE_AA)
            cv2.putText(big, num, (8, big.shape[0] - 10), cv2.FONT_HERSHEY_DUPLEX, 1.2, (255, 255, 255), 1,
                        cv2.LINE_AA)
            tiles.append(big)
            dist = float(np.sqrt(((key - ref) ** 2).sum(axis=1).mean()))       # RMS point distance, model units
            captions.append(f"{name}  frame {int(f)}" + ("" if exact else " (cluster mean)")
                            + ("" if name.endswith("neutral") else f"  d={dist:.1f}"))
    return tiles, captions


def key_sheet(video_path, tracks: Tracks, scheme: Scheme, regions: list[RegionKeys], columns: int = 4,
              tile_width: int = 280, poses: np.ndarray | None = None) -> np.ndarray:
    """The sheet image (BGR uint8) for ``regions``' keys, frames decoded from ``video_path``
    (``poses``: as :func:`key_tiles`)."""
    from keyshape.base.formats.video import VideoReader

    wanted = sorted({int(f) for rk in regions for f in rk.frames}
                    | {int(rk.rest_frame) for rk in regions if rk.rest_frame is not None})
    images = VideoReader(video_path).read_frames(wanted)
    tiles, captions = key_tiles(dict(zip(wanted, images)), tracks, scheme, regions, tile_width, poses)
    return contact_sheet(tiles, captions, columns=columns, tile_width=tile_width)
