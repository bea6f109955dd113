"""Live Link Face: the CSV the iPhone app records and the UDP packets it streams to Unreal.

Design notes and figures: docs/formats.md, "Notes on the code", ``keyshape/base/formats/livelink.py``.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from fractions import Fraction
from typing import Sequence

import numpy as np

from keyshape.base.errors import InputError

# ARKit's 52 names in the order of the Live Link Face CSV (PascalCase there).
ARKIT52 = (
    "eyeBlinkLeft eyeLookDownLeft eyeLookInLeft eyeLookOutLeft eyeLookUpLeft eyeSquintLeft eyeWideLeft "
    "eyeBlinkRight eyeLookDownRight eyeLookInRight eyeLookOutRight eyeLookUpRight eyeSquintRight eyeWideRight "
    "jawForward jawRight jawLeft jawOpen mouthClose mouthFunnel mouthPucker mouthRight mouthLeft "
    "mouthSmileLeft mouthSmileRight mouthFrownLeft mouthFrownRight mouthDimpleLeft mouthDimpleRight "
    "mouthStretchLeft mouthStretchRight mouthRollLower mouthRollUpper mouthShrugLower mouthShrugUpper "
    "mouthPressLeft mouthPressRight mouthLowerDownLeft mouthLowerDownRight mouthUpperUpLeft mouthUpperUpRight "
    "browDownLeft browDownRight browInnerUp browOuterUpLeft browOuterUpRight cheekPuff cheekSquintLeft "
    "cheekSquintRight noseSneerLeft noseSneerRight tongueOut").split()
LIVELINK_TAIL = ("HeadYaw HeadPitch HeadRoll LeftEyeYaw LeftEyePitch LeftEyeRoll "
                 "RightEyeYaw RightEyePitch RightEyeRoll").split()
#: The 61 CSV value columns (after Timecode and BlendShapeCount), PascalCase.
CSV_NAMES = [n[0].upper() + n[1:] for n in ARKIT52] + LIVELINK_TAIL
#: The 61 values of a packet, in Unreal's ``EARFaceBlendShape`` order.
PACKET_NAMES = (
    "EyeBlinkLeft EyeLookDownLeft EyeLookInLeft EyeLookOutLeft EyeLookUpLeft EyeSquintLeft EyeWideLeft "
    "EyeBlinkRight EyeLookDownRight EyeLookInRight EyeLookOutRight EyeLookUpRight EyeSquintRight EyeWideRight "
    "JawForward JawLeft JawRight JawOpen MouthClose MouthFunnel MouthPucker MouthLeft MouthRight "
    "MouthSmileLeft MouthSmileRight MouthFrownLeft MouthFrownRight MouthDimpleLeft MouthDimpleRight "
    "MouthStretchLeft MouthStretchRight MouthRollLower MouthRollUpper MouthShrugLower MouthShrugUpper "
    "MouthPressLeft MouthPressRight MouthLowerDownLeft MouthLowerDownRight MouthUpperUpLeft MouthUpperUpRight "
    "BrowDownLeft BrowDownRight BrowInnerUp BrowOuterUpLeft BrowOuterUpRight CheekPuff CheekSquintLeft "
    "CheekSquintRight NoseSneerLeft NoseSneerRight TongueOut").split() + LIVELINK_TAIL
PACKET_VERSION = 6
N_VALUES = 61
DEFAULT_PORT = 11111
#: packet index of every CSV column: ``packet[CSV_TO_PACKET] = csv_values``
CSV_TO_PACKET = np.array([PACKET_NAMES.index(n) for n in CSV_NAMES])


def timecode(index: int, fps: float) -> str:
    """``HH:MM:SS:FF.sss`` of frame ``index`` at ``fps`` (the CSV's Timecode column)."""
    t = index / fps
    sec = int(t)
    ff = int(round((t - sec) * fps, 6))
    sub = (t - sec) * fps - ff
    return f"{sec // 3600:02d}:{sec // 60 % 60:02d}:{sec % 60:02d}:{ff:02d}.{int(round(sub * 1000)):03d}"


def csv_rows(values: np.ndarray, fps: float) -> tuple[list[str], list[list[str]]]:
    """Header and rows of a Live Link Face CSV for ``values`` (n_frames, 61) in CSV column order."""
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != N_VALUES:
        raise InputError(f"Live Link values: expected (n_frames, {N_VALUES}), got {v.shape}")
    header = ["Timecode", "BlendShapeCount"] + CSV_NAMES
    rows = [[timecode(i, fps), str(N_VALUES)] + ["%.6g" % x for x in row] for i, row in enumerate(v)]
    return header, rows


def write_csv(path, values: np.ndarray, fps: float) -> None:
    """Write the Live Link Face CSV of ``values`` (n_frames, 61; :func:`csv_rows`) atomically."""
    import csv

    from keyshape.base.files import atomic_write
    header, rows = csv_rows(values, fps)
    with atomic_write(path, newline="") as f:
        csv.writer(f).writerows([header, *rows])


def csv_to_packet(values: np.ndarray) -> np.ndarray:
    """(..., 61) values in CSV column order -> the packet's order."""
    v = np.asarray(values)
    out = np.empty_like(v)
    out[..., CSV_TO_PACKET] = v
    return out


def rate_fraction(fps: float) -> tuple[int, int]:
    """The frame rate as (numerator, denominator): 30 -> (30, 1); the NTSC rates (23.976, 29.97, 59.94,
    as containers round them) -> (24000, 1001), (30000, 1001), (60000, 1001)."""
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"frame rate must be > 0, got {fps}")
    for num in (24000, 30000, 48000, 60000, 120000):
        if abs(fps - num / 1001) < 0.005:
            return num, 1001
    f = Fraction(float(fps)).limit_denominator(1000)
    return f.numerator, f.denominator


def encode_packet(values: Sequence[float], frame: int, fps: float, subject: str = "keyshape",
                  device_id: str = "keyshape", subframe: float = 0.0) -> bytes:
    """One Live Link Face UDP packet (layout: module docstring).

    Parameters
    ----------
    values : 61 values in :data:`PACKET_NAMES` order (blend shapes 0..1, angles in radians)
    frame : frame number of the frame time; fps : its frame rate (sent as a fraction)
    subject : the Live Link subject name Unreal lists; device_id : the sender's id
    subframe : fraction of a frame
    """
    v = np.asarray(values, dtype=">f4")
    if v.shape != (N_VALUES,):
        raise InputError(f"Live Link packet: expected {N_VALUES} values, got {v.shape}")
    dev, sub = device_id.encode("utf-8"), subject.encode("utf-8")
    num, den = rate_fraction(fps)
    return b"".join([struct.pack(">Bi", PACKET_VERSION, len(dev)), dev, struct.pack(">i", len(sub)), sub,
                     struct.pack(">ifiiB", int(frame), float(subframe), num, den, N_VALUES), v.tobytes()])


@dataclass
class Packet:
    """A decoded Live Link Face packet (see :func:`decode_packet`)."""

    version: int
    device_id: str
    subject: str
    frame: int
    subframe: float
    rate: tuple
    values: np.ndarray          # (61,) float32 in PACKET_NAMES order

    @property
    def fps(self) -> float:
        return self.rate[0] / self.rate[1]

    def named(self) -> dict[str, float]:
        """``{PascalCase name: value}``."""
        return {n: float(x) for n, x in zip(PACKET_NAMES, self.values)}


def decode_packet(data: bytes) -> Packet:
    """Read one Live Link Face UDP packet (written from the layout above, not from :func:`encode_packet`).

    Raises :class:`InputError` for a packet too short, of another version or blend shape count.
    """
    def take(fmt, at):
        n = struct.calcsize(fmt)
        if at + n > len(data):
            raise InputError(f"Live Link packet truncated at byte {at} ({len(data)} bytes)")
        return struct.unpack_from(fmt, data, at), at + n

    (version,), at = take(">B", 0)
    if version != PACKET_VERSION:
        raise InputError(f"Live Link packet version {version}, expected {PACKET_VERSION}")
    strings = []
    for _ in range(2):
        (n,), at = take(">i", at)
        if n < 0 or at + n > len(data):
            raise InputError(f"Live Link packet: string length {n} at byte {at - 4} is out of the packet")
        strings.append(data[at:at + n].decode("utf-8", errors="replace"))
        at += n
    (frame, subframe, num, den, count), at = take(">ifiiB", at)
    if count != N_VALUES or den <= 0:
        raise InputError(f"Live Link packet: {count} blend shapes at rate {num}/{den}, expected {N_VALUES}")
    vals, at = take(f">{count}f", at)
    if at != len(data):
        raise InputError(f"Live Link packet: {len(data) - at} bytes after the values")
    return Packet(version, strings[0], strings[1], frame, subframe, (num, den), np.array(vals, np.float32))
