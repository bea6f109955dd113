"""Command-line option checks shared by every command, as argparse ``type=`` functions.

One function per kind of value, so that one option means the same in every command (``--fps`` in
``solve`` as in ``retarget`` and ``synth video``) and is refused, with one line naming the option,
before the command reads a single frame. argparse reports a refusal as
``keyshape COMMAND: error: argument --fps: ...`` (exit 2; ``keyshape.cli`` makes it one line).
"""
from __future__ import annotations

import argparse
import math
from typing import Callable

#: frame rates any command accepts (frames per second): from time-lapse to high-speed cameras
FPS_MIN = 0.1
FPS_MAX = 1000.0
#: most frames a synthetic take may have (each frame is rendered and held for the labels and truth)
SYNTH_FRAMES_MAX = 100_000
#: largest ``--head-units`` (pixels of the actor's head per unit) accepted
HEAD_UNITS_MAX = 1e6


def _number(text: str, what: str) -> float:
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"{text!r}: {what} must be a number") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text}: {what} must be a finite number")
    return v


def fps(text: str) -> float:
    """A frame rate: finite, from :data:`FPS_MIN` to :data:`FPS_MAX`."""
    v = _number(text, "a frame rate")
    if not FPS_MIN <= v <= FPS_MAX:
        raise argparse.ArgumentTypeError(f"{text}: a frame rate must be from {FPS_MIN:g} to {FPS_MAX:g} frames "
                                         "per second")
    return v


def positive(upper: float, what: str = "the value") -> Callable[[str], float]:
    """A finite number in (0, ``upper``]."""
    def check(text: str) -> float:
        v = _number(text, what)
        if not 0 < v <= upper:
            raise argparse.ArgumentTypeError(f"{text}: {what} must be > 0 and at most {upper:g}")
        return v
    check.__name__ = "positive"
    return check


head_units = positive(HEAD_UNITS_MAX, "the head units (mesh units per tracker unit)")


def whole(lo: int, hi: int, what: str = "the count") -> Callable[[str], int]:
    """A whole number from ``lo`` to ``hi`` (``1e3`` is read as 1000 when it is whole)."""
    def check(text: str) -> int:
        try:
            v = int(text)
        except (TypeError, ValueError):
            f = _number(text, what)
            if f != int(f):
                raise argparse.ArgumentTypeError(f"{text}: {what} must be a whole number") from None
            v = int(f)
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"{text}: {what} must be from {lo} to {hi}")
        return v
    check.__name__ = "whole"
    return check


#: a TCP/UDP port: 0 (any free port) to 65535
port = whole(0, 65535, "a port")
synth_frames = whole(1, SYNTH_FRAMES_MAX, "the number of frames")
