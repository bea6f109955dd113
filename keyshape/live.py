"""``keyshape live``: a camera (or a video played at its own rate) to a rig's curves, streamed as it happens.

Design notes and figures: docs/live.md, "Notes on the code", ``keyshape/live.py``.
"""
from __future__ import annotations

import argparse
import re
import socket
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base import options
from keyshape.decompose import defaults as D
from keyshape.retarget.defaults import GAZE, GAZES, SolveOptions

#: the head sent: the 3D head and gaze from a calibration, or the 2D head's roll
LIVE_HEADS = ("3d", "2d")
#: most calibration frames (evenly spaced) whose head-frame shapes set the gaze's straight-ahead live
GAZE_FRAMES = 301


# ----------------------------------------------------------------------------------------------- sources
#: highest camera number accepted as a source (OpenCV's device indices are small integers)
CAMERA_MAX = 9999


def _is_camera(source: str) -> bool:
    """Whether ``source`` is a camera number (one-line error above :data:`CAMERA_MAX`) rather than a file."""
    camera = re.fullmatch(r"\d+", str(source)) is not None
    if camera and int(source) > CAMERA_MAX:
        raise InputError(f"camera {source}: a camera number is from 0 to {CAMERA_MAX} (or give a video file)")
    return camera


class FrameSource:
    """Frames of a camera (OpenCV device index) or of a video file, with their capture times.

    Iterating yields ``(index, frame)`` like :class:`keyshape.base.formats.video.VideoReader`. A file is played at
    its own frame rate (``pace``): a frame more than one frame period late when decoded is dropped and counted as
    lost, as a camera drops frames; ``pace=False`` hands over every frame (tests). A camera's lost frames are the
    gaps between capture times longer than 1.5 frame periods.

    Attributes
    ----------
    info : ``fps``, ``width``, ``height`` (an object like :class:`~keyshape.base.formats.video.VideoInfo`)
    luma_table : a file's frames are its luma plane through this table, gray, as ``keyshape track`` decodes
        them (:func:`~keyshape.base.formats.video.luma_table`); None: BGR frames (a camera, or a file the
        table does not fit)
    captured : {index: ``time.perf_counter()`` when the frame was captured (or became due)}
    lost : frames dropped or missed so far
    """

    def __init__(self, source: str, pace: bool = True, max_frames: int | None = None):
        import cv2
        self.camera = _is_camera(source)
        self.pace, self.max_frames = pace, max_frames
        self.luma_table = None
        if self.camera:
            from keyshape.base.formats.video import opencv_log
            with opencv_log(cv2.utils.logging.LOG_LEVEL_SILENT):   # the one-line error says what failed
                cap = cv2.VideoCapture(int(source))
                ok = cap.isOpened() and cap.read()[0]
            if not ok:
                cap.release()
                raise InputError(f"camera {source}: cannot open it (no such device, or it is busy)")
            self.name = f"camera {source}"
        else:
            from keyshape.base.formats.video import luma_table, open_capture, video_info
            video_info(source)                                     # one-line errors naming the file
            # a file is decoded as `keyshape track` decodes it (the luma plane alone where it gives the gray),
            # so that live and offline see the same gray levels
            self.luma_table = luma_table(source)
            cap = open_capture(require_file(source, "video"), self.luma_table)
            self.name = str(source)
        self.cap = cap
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.info = SimpleNamespace(fps=fps if np.isfinite(fps) and 1.0 <= fps <= 1000.0 else 30.0,
                                    width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                                    height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        self.captured: dict[int, float] = {}
        self.lost = 0
        self.n_read = 0

    def __iter__(self):
        from keyshape.base.formats.video import read_frame
        period = 1.0 / self.info.fps
        t0 = last = None
        i = -1
        try:
            while self.max_frames is None or self.n_read < self.max_frames:
                ok, frame = read_frame(self.cap, self.luma_table)
                if not ok:
                    return
                i += 1
                now = time.perf_counter()
                if self.camera:
                    if last is not None and now - last > 1.5 * period:
                        self.lost += int(round((now - last) / period)) - 1
                    last = now
                elif self.pace:
                    if t0 is None:
                        t0 = now
                    due = t0 + i * period
                    if now > due + period:                         # late by more than a frame: dropped
                        self.lost += 1
                        continue
                    if now < due:
                        time.sleep(due - now)
                    now = time.perf_counter()
                self.captured[i] = now
                if len(self.captured) > 256:
                    self.captured.pop(next(iter(self.captured)))
                self.n_read += 1
                yield i, frame
        finally:
            self.cap.release()


# ------------------------------------------------------------------------------------------------ sinks
def parse_host_port(text: str, what: str) -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port) with a one-line error naming ``what``."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"{what} {text!r}: expected HOST:PORT with a port in 1..65535")
    return host, int(port)


def _resolve(host: str, port: int, what: str):
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
    except socket.gaierror as exc:
        raise InputError(f"{what}: cannot resolve host {host!r} ({exc.strerror})") from None
    return infos[0]


class LiveLinkSender:
    """A UDP socket sending Live Link Face packets to ``host:port`` (bound to ``local_port`` if given)."""

    def __init__(self, host: str, port: int, local_port: int | None = None, subject: str = "keyshape"):
        family, _, _, _, addr = _resolve(host, port, "--host")
        self.target = f"{host}:{port}"
        self.subject = subject
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            if local_port is not None:
                try:
                    self.sock.bind(("", local_port))
                except OSError as exc:
                    raise InputError(f"--local-port {local_port}: cannot bind it ({exc.strerror}; is the port "
                                     "in use?)") from None
            try:
                self.sock.connect(addr)
            except OSError as exc:
                raise InputError(f"--host {host}: unreachable ({exc.strerror})") from None
        except BaseException:
            self.sock.close()
            raise

    def send(self, packet: bytes) -> None:
        try:
            self.sock.send(packet)
        except ConnectionRefusedError:          # nobody listening (yet): Unreal may start later
            pass
        except OSError as exc:
            raise InputError(f"cannot send to {self.target}: {exc.strerror}") from None

    def close(self) -> None:
        self.sock.close()


class OscSender:
    """One OSC message per curve, ``PREFIX/<curve name> <float>``, to ``host:port`` (python-osc)."""

    def __init__(self, host: str, port: int, prefix: str = "/keyshape"):
        try:
            from pythonosc.udp_client import SimpleUDPClient
        except ImportError:
            raise InputError("--osc needs python-osc: pip install 'keyshape[osc]'") from None
        _resolve(host, port, "--osc")
        self.client = SimpleUDPClient(host, port)
        self.prefix = "/" + prefix.strip("/")

    def send(self, names, values) -> None:
        for n, v in zip(names, values):
            try:
                self.client.send_message(f"{self.prefix}/{n}", float(v))
            except ConnectionRefusedError:
                pass
            except OSError as exc:
                raise InputError(f"--osc: cannot send ({exc.strerror})") from None

    def close(self) -> None:
        self.client._sock.close()


# ------------------------------------------------------------------------------------------- the chain
class LiveHead:
    """The 3D head's angles and the eyes' angles of one frame, from a calibration fitted offline, once.

    The take's 3D head (:meth:`keyshape.decompose.take.Take.fit`: the actor's 3D face, the camera, the front-facing
    zero) is fitted on a calibration take; each live frame is posed alone by it with its temporal smoothing off
    (:func:`~keyshape.retarget.api.head_from_tracks` on the one frame). The gaze is
    :func:`keyshape.decompose.gaze.gaze_angles` of the frame with the calibration's head-frame shapes before it
    (twice, so their median is the calibration's; at most :data:`GAZE_FRAMES` of them); a closed eye holds the live
    run's last open gaze (before the first: the calibration's straight-ahead gaze).

    Parameters
    ----------
    estimator : a fitted :class:`~keyshape.decompose.head3d.HeadPose3D` (copied; its smoothing set to 0)
    calibration : the calibration's :class:`~keyshape.base.formats.tracks.Tracks` (for the gaze)
    scheme : their :class:`~keyshape.base.schemes.Scheme`
    gaze : ``angles``, ``shapes`` or ``none`` (as ``retarget --gaze``)
    source : the calibration file, named in errors
    """

    def __init__(self, estimator, calibration, scheme, gaze: str = "angles", source=None):
        import copy

        from keyshape.decompose.gaze import gaze_angles, has_gaze
        from keyshape.decompose.regions import fitted_head_points

        est = copy.copy(estimator)
        est.smooth = 0.0                                  # causal: each frame posed alone
        self.estimator, self.scheme, self.gaze, self.source = est, scheme, gaze, source
        self.context = None                               # calibration shapes (twice) + a slot for the frame
        self.last_head = None                             # the last frame's head (held where a pose fails)
        self.last_eyes = np.zeros(4)
        self.note = ""
        if gaze == "none":
            return
        if not has_gaze(scheme):
            self.note = f"scheme {scheme.name!r} has no pupils: no eye angles"
            return
        H = est.transform(fitted_head_points(est, calibration, source))[:, :calibration.n_points]
        H = H[np.isfinite(H).all(axis=(1, 2))]
        if len(H) > GAZE_FRAMES:                          # the per-frame cost grows with the context
            H = H[np.unique(np.linspace(0, len(H) - 1, GAZE_FRAMES).round().astype(int))]
        g = gaze_angles(H, scheme)
        # an open frame of both eyes (gaze_angles gives a closed eye the last open frame's value): the one
        # looking most straight ahead goes last, so that a closed eye in the live frame is seen as a copy of it
        fresh = np.ones((len(g), 2), bool)
        fresh[1:] = (g[1:].reshape(-1, 2, 2) != g[:-1].reshape(-1, 2, 2)).any(-1)
        fresh[0] = False
        both = np.flatnonzero(fresh.all(1) & np.isfinite(g).all(1))
        if not len(both):
            self.note = f"no frame of the calibration {source} has both eyes open: no eye angles"
            return
        a = int(both[np.argmin(np.abs(g[both]).sum(1))])
        order = np.r_[np.delete(np.arange(len(H)), a), a]
        self.context = np.concatenate([H, H[order], H[:1]])
        self.last_eyes = g[a].copy()

    def frame(self, tracks) -> tuple:
        """``(HeadMotion, eye angles (4,) or None)`` of a one-frame :class:`~keyshape.base.formats.tracks.Tracks`."""
        from keyshape.decompose.gaze import gaze_angles
        from keyshape.retarget.api import head_from_tracks

        try:
            head = head_from_tracks(tracks, tracks.frame, None, 1.0, self.source, head=self.estimator)
            self.last_head = head
        except InputError:                                 # no pose found: hold the last one (offline holds too)
            head = self.last_head
        if self.context is None:
            return head, None
        from keyshape.decompose.regions import fitted_head_points
        self.context[-1] = self.estimator.transform(fitted_head_points(self.estimator, tracks))[0, :tracks.n_points]
        g = gaze_angles(self.context, self.scheme)[-2:]
        eyes = g[1].copy()
        for c in (slice(0, 2), slice(2, 4)):
            if (g[1, c] == g[0, c]).all():                 # closed: the last open frame's gaze
                eyes[c] = self.last_eyes[c]
        self.last_eyes = eyes
        return head, eyes


def calibration_tracks(calibration, keys_path, scheme_name: str, model: str | None = None):
    """``(tracks, path)`` of the calibration take: ``calibration``, else the key set's own tracks (KEYS.json's
    ``source``); one-line errors where there are none, they are another model's (``model``: the live model's
    fingerprint, :func:`keyshape.tracker.commands.model_fingerprint`) or of another scheme."""
    from pathlib import Path

    from keyshape.base.files import found_beside
    from keyshape.base.formats.keys import read_keys_source
    from keyshape.base.formats.tracks import read_tracks
    from keyshape.base.schemes import load_scheme

    if calibration is None:
        listed = read_keys_source(keys_path).get("tracks") or []
        calibration = found_beside(listed[0], Path(keys_path).parent) if listed else None
        if calibration is None:
            why = "the key set names none" if not listed else f"{listed[0]} is gone"
            raise InputError(f"keyshape live solves with the statistics of a calibration take and has none ({why}): "
                             "give --calibration TRACKS.csv (the actor tracked with this model)", keys_path)
    calibration = require_file(calibration, "calibration tracks")
    tracks = read_tracks(calibration)
    made = tracks.meta.get("model")
    if model and made and made != model:
        raise InputError(f"the calibration tracks come from another tracker model ({made}; the live model: {model}): "
                         "track the calibration take with the live model", calibration)
    scheme = load_scheme(scheme_name)
    if tracks.n_points != scheme.n_points:
        raise InputError(f"the calibration tracks have {tracks.n_points} points but the key set's scheme "
                         f"{scheme_name!r} {scheme.n_points}: track the calibration take with the live model",
                         calibration)
    return tracks, calibration


def load_head(take, scheme, gaze: str = "angles", say=None) -> LiveHead | None:
    """The :class:`LiveHead` of the calibration ``take`` (a :class:`~keyshape.decompose.take.Take`: its fitted
    3D head), or None (the 2D head roll) where its scheme has no 3D face; what happened is said in one line
    through ``say``."""
    say = say or (lambda line: print(line, file=sys.stderr))
    tracks, calibration, est = take.tracks, take.source, take.head3d
    if est is None:
        say(f"keyshape live: scheme {scheme.name!r} has no 3D face (or {calibration} no tracked frame): "
            "sending the 2D head roll and no eye angles")
        return None
    head = LiveHead(est, tracks, scheme, gaze, calibration)
    say(f"keyshape live: 3D head and {'eye angles' if head.context is not None else 'no eye angles'} "
        f"calibrated on {calibration} ({int(tracks.success.sum())} frames){'; ' + head.note if head.note else ''}")
    return head


@dataclass
class LiveChain:
    """The offline chain for one frame at a time: the rig's per-frame solve -> (the pose library) -> Live Link values.

    Built by :func:`load_chain`; :meth:`frame` runs it on one tracked frame. ``solve``: ``keyshape solve``'s
    solve fitted on the calibration take (:class:`~keyshape.retarget.api.TakeSolve`); ``library``: the artist's
    pose library over it (None: none), with the calibration's curves at its keys (``key_curves``, rows of
    ``key_frames``); ``head``: the 3D head and gaze (:class:`LiveHead`); None: the 2D head's roll, relative to the
    first frame, no eye angles.
    """

    scheme: str
    regions: list
    head_pose: dict | None
    rig_names: list
    solve: object
    library: dict | None = None
    key_frames: dict = field(default_factory=dict)
    key_curves: np.ndarray | None = None
    reference_pose: np.ndarray | None = field(default=None)
    head: LiveHead | None = None
    model_scheme: object = None                       # the model's Scheme: its auxiliary points (the nose) split off

    def frame(self, index: int, fps: float, points: np.ndarray, res) -> tuple[np.ndarray, np.ndarray]:
        """(rig curves (n_shapes,), Live Link values (61,) in CSV column order) of one tracked frame."""
        from keyshape.base.formats.tracks import Tracks
        from keyshape.retarget.output.export import livelink_values

        p, aux = points[None].astype(np.float64), {}
        if self.model_scheme is not None:                  # the model's nose points: the 3D head's too
            p, aux = self.model_scheme.split(p)
        tr = Tracks(np.array([index]), np.array([index / fps]), np.array([res.confidence]), np.array([True]),
                    p, np.asarray(res.pose, np.float64)[None], {"scheme": self.scheme}, aux)
        if self.head is not None:
            head, eyes = self.head.frame(tr)
        else:
            head, eyes = self._head_2d(tr), None
        curves = self.solve.curves(tr, None if eyes is None else eyes[None])
        if self.library is not None:
            curves = self._override(tr, curves)
        return curves[0], livelink_values(self.rig_names, curves, head, None if eyes is None else eyes[None])[0]

    def _override(self, tr, curves: np.ndarray) -> np.ndarray:
        """The pose library over one frame's solved curves, as ``solve --poses --weights`` does offline
        (:func:`~keyshape.retarget.rig.solve.pose_override`): the frame's key weights, the calibration's curves at
        the keys."""
        from keyshape.decompose.api import decompose_keys
        from keyshape.retarget.rig.solve import pose_override

        columns, w = decompose_keys(tr, self.regions, "nnls", 0.1, D.RIDGE, None, self.head_pose)
        frames = np.r_[np.array(sorted(set(self.key_frames.values())), np.int64), -1]
        weights = np.vstack([np.zeros((len(frames) - 1, w.shape[1])), w])
        out = pose_override(np.vstack([self.key_curves, curves]), frames, weights, columns, self.library,
                            self.rig_names, self.key_frames)
        return out[-1:]

    def _head_2d(self, tr):
        """The in-plane head motion of a one-frame track relative to the run's first frame."""
        from keyshape.decompose.regions import stable_pose
        from keyshape.retarget.headpose import HeadMotion, head_motion

        pose = stable_pose(tr, self.head_pose)[0]
        if self.reference_pose is None:
            self.reference_pose = pose
        hm = head_motion(np.stack([pose, self.reference_pose]), reference=1)
        return HeadMotion(hm.translation[:1], hm.rotation[:1], hm.scale[:1], hm.angle[:1])


def load_chain(model_path, keys_path, rig, *, poses=None, calibration=None, head: str = "3d",
               options: SolveOptions = SolveOptions(), neutral=None, say=None):
    """Read the model, key set, rig and (``poses``) pose library; check they belong together (one-line errors);
    fit ``keyshape solve``'s solve (``options``) on the calibration tracks (``calibration``, default the key set's
    own, :func:`calibration_tracks`) and, with ``head="3d"``, the 3D head and gaze (:func:`load_head`; ``"2d"``: the
    head's roll only).

    Returns ``(model, chain)``.
    """
    import copy

    from keyshape.base.formats.keys import read_keys, read_keys_head_pose
    from keyshape.base.formats.poses import read_poses
    from keyshape.base.schemes import load_scheme
    from keyshape.decompose.take import Take
    from keyshape.retarget.api import fit_solve
    from keyshape.retarget.output.export import livelink_values
    from keyshape.retarget.rig.model import load_rig
    from keyshape.tracker.eigenpoints import AppearanceModel

    if head not in LIVE_HEADS:
        raise InputError(f"head {head!r}: use one of {', '.join(LIVE_HEADS)}")
    if options.gaze not in GAZES:
        raise InputError(f"--gaze {options.gaze}: use one of {', '.join(GAZES)}")
    scheme, n_points, regions = read_keys(keys_path)
    head_entry = read_keys_head_pose(keys_path)
    from keyshape.base.formats.model import read_model
    mf = read_model(model_path)                                   # its scheme, before the model is built
    if mf.scheme.base_name != scheme or mf.scheme.core != n_points:
        raise InputError(f"the model tracks scheme {mf.scheme.name!r} ({mf.scheme.n_points} points) but the key "
                         f"set {keys_path} is of scheme {scheme!r} ({n_points} points): use the model and keys "
                         "of one actor and scheme", model_path)
    model = AppearanceModel.from_file(mf)
    rig_obj = load_rig(rig, neutral, with_mesh=False)
    livelink_values(rig_obj.names, np.zeros((1, rig_obj.n_shapes)))   # the rig has ARKit names, or one line
    lib = read_poses(poses, rig_obj.names) if poses else None
    from keyshape.tracker.commands import model_fingerprint
    tracks, cal_path = calibration_tracks(calibration, keys_path, scheme, model_fingerprint(model))
    take = Take.fit(tracks, cal_path)                   # fitted once: the solve's statistics and the head
    report: dict = {}
    solve, *_ = fit_solve(take, regions, scheme, head_entry, rig_obj, options, report=report)
    if solve.estimator is not None:                   # each frame's yaw posed alone (live has no future frame)
        solve.estimator = copy.copy(solve.estimator)
        solve.estimator.smooth = 0.0
    say = say or (lambda line: print(line, file=sys.stderr))
    for line in report.get("eyes", []):
        say(f"keyshape live: {line.describe()}")
    key_frames, key_curves = {}, None
    if lib is not None:
        pos = {int(f): i for i, f in enumerate(tracks.frame)}
        key_frames = {k: int(f) for rk in regions for k, f in zip(rk.names, rk.frames)}
        missing = sorted({f for f in key_frames.values() if f not in pos})
        if missing:
            raise InputError(f"--poses: the keys' frames {missing[:5]} are not frames of the calibration {cal_path}: "
                             "calibrate on the key set's own tracks", poses)
        key_curves = solve.curves_[[pos[f] for f in sorted(set(key_frames.values()))]]
    live_head = load_head(take, load_scheme(scheme), options.gaze, say) if head == "3d" else None
    chain = LiveChain(scheme, regions, head_entry, list(rig_obj.names), solve, lib, key_frames, key_curves,
                      head=live_head, model_scheme=mf.scheme)
    return model, chain


# -------------------------------------------------------------------------------------------- the loop
@dataclass
class LiveStats:
    """What a live run did: frames tracked and sent, lost frames, latencies (seconds), send times."""

    frames: int = 0
    lost: int = 0
    face_lost_frames: int = 0
    latencies: list = field(default_factory=list)
    first_send: float | None = None
    last_send: float | None = None
    recent: deque = field(default_factory=lambda: deque(maxlen=61))

    def record(self, t_sent: float, latency: float | None) -> None:
        """Count one frame sent at ``t_sent`` (``time.perf_counter()``), ``latency`` after its capture."""
        if self.first_send is None:
            self.first_send = t_sent
        self.last_send = t_sent
        self.recent.append(t_sent)
        if latency is not None:
            self.latencies.append(latency)
        self.frames += 1

    @property
    def fps(self) -> float:
        """Frames per second sustained from the first frame sent to the last."""
        if self.first_send is None or self.last_send <= self.first_send:
            return 0.0
        return (self.frames - 1) / (self.last_send - self.first_send)

    def line(self, face_ok: bool = True, final: bool = False) -> str:
        """The status line: the last 60 frames' rate and median latency (the whole run's when ``final``)."""
        r = self.recent
        fps = self.fps if final or len(r) < 2 else (len(r) - 1) / max(r[-1] - r[0], 1e-9)
        lat = np.array(self.latencies if final else self.latencies[-60:]) * 1e3
        med = f"{np.median(lat):.1f}" if len(lat) else "-"
        return (f"keyshape live: {self.frames} frames, {fps:.1f} fps, latency {med} ms (median), lost {self.lost}, "
                f"face {'tracked' if face_ok else 'LOST (sending neutral)'}")


def stream(source: FrameSource, model, chain: LiveChain, sender: LiveLinkSender, osc: OscSender | None = None,
           status="stderr", status_every: float = 0.5, smooth: str = "none") -> LiveStats:
    """Track ``source`` frame by frame and send every frame's packet; returns the run's :class:`LiveStats`.

    ``status``: a text stream for the status line (refreshed in place on a terminal, printed once at the
    end otherwise), ``"stderr"`` (default: ``sys.stderr`` at call time) or None (silent). Ctrl-C ends the
    stream: the stats so far are printed and ``KeyboardInterrupt`` is raised again.
    """
    if status == "stderr":
        status = sys.stderr
    from keyshape.base.formats.livelink import csv_to_packet, encode_packet
    from keyshape.tracker.commands import iter_track
    from keyshape.tracker.defaults import TrackOptions

    fps = source.info.fps
    stats = LiveStats()
    neutral = np.zeros(61)
    zero_curves = np.zeros(len(chain.rig_names))
    face_ok, last_status = True, 0.0
    tty = hasattr(status, "isatty") and status.isatty()

    def show(final=False):
        stats.lost = source.lost
        if status is None:
            return
        text = stats.line(face_ok, final)
        status.write(("\r" + text + "\x1b[K" if tty else text) + ("\n" if final or not tty else ""))
        status.flush()

    try:
        for pts, res, _ in iter_track(None, model, TrackOptions(smooth, decode_thread=False), reader=source):
            if res.success and np.isfinite(pts).all():
                curves, values = chain.frame(res.index, fps, pts, res)
                if not face_ok and status is not None:
                    status.write(("\n" if tty else "") + f"keyshape live: face found again at frame {res.index}\n")
                face_ok = True
            else:
                curves, values = zero_curves, neutral
                if face_ok and status is not None:
                    status.write(("\n" if tty else "") + f"keyshape live: face lost at frame {res.index}: sending "
                                 "the neutral until it is found\n")
                face_ok = False
                stats.face_lost_frames += 1
            sender.send(encode_packet(csv_to_packet(values), res.index, fps, subject=sender.subject))
            if osc is not None:
                osc.send(chain.rig_names, curves)
            t = time.perf_counter()
            cap = source.captured.get(res.index)
            stats.record(t, None if cap is None else t - cap)
            if t - last_status >= status_every:
                last_status = t
                if tty:
                    show()
    except KeyboardInterrupt:
        show(final=True)
        raise
    show(final=True)
    return stats


def register(subparsers) -> None:
    """Add ``live`` to ``subparsers``."""
    p = subparsers.add_parser(
        "live", help="stream a camera (or a video at its own rate) to a rig's curves over Live Link Face UDP",
        description="Track a camera (OpenCV device index) or a video file frame by frame with a trained model, "
                    "solve the rig's curves of every frame as keyshape solve does (its statistics fitted once on a "
                    "calibration take), and send every frame as a Live Link Face UDP packet (Unreal's Live Link "
                    "Face source) and, with --osc, as OSC messages. Ctrl-C stops.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("source", help="camera index (0, 1, ...) or a video file (played at its own frame rate)")
    p.add_argument("--model", required=True, help="tracker model from keyshape train")
    p.add_argument("--keys", required=True, help="KEYS.json from keyshape select")
    p.add_argument("--rig", required=True, nargs="+", metavar="DIR|FILE", help="the rig (as for solve --rig)")
    p.add_argument("--landmarks", default=None,
                   help="rig landmark JSON (default: the shipped correspondence for ICT-FaceKit rigs)")
    p.add_argument("--poses", help="POSES.json (keyshape pose, corrected by hand): the artist's poses over the solve "
                                   "at their keys, as solve --poses")
    p.add_argument("--calibration", metavar="TRACKS.csv",
                   help="tracks of the actor in front of this camera (keyshape track with this model), on which the "
                        "solve's statistics (each eye's deepest closure, the rest), the 3D face, the camera and the "
                        "front-facing zero are fitted once (default: the key set's own tracks, as KEYS.json names them)")
    p.add_argument("--gaze", choices=GAZES, default=GAZE,
                   help="the pupils' gaze (as solve --gaze): angles (the Live Link eye angles), shapes (also the "
                        "rig's eyeLook* curves) or none")
    p.add_argument("--host", default="127.0.0.1", help="where Unreal listens (the Live Link Face source)")
    p.add_argument("--port", type=options.port, default=11111, help="its UDP port")
    p.add_argument("--subject", default="keyshape", help="the Live Link subject name Unreal shows")
    p.add_argument("--osc", metavar="HOST:PORT", help="also send OSC: one message per rig curve, /keyshape/<curve> "
                                                      "(needs python-osc: pip install 'keyshape[osc]')")
    p.add_argument("--no-pace", action="store_true",
                   help="a video file: hand over frames as fast as they decode instead of at the video's rate")
    p.set_defaults(func=run)


def run(args) -> int:
    if not 0 < args.port < 65536:
        raise InputError(f"--port {args.port}: must be in 1..65535")
    if not _is_camera(args.source):
        require_file(args.source, "video")
    osc_addr = parse_host_port(args.osc, "--osc") if args.osc else None
    notes: list[str] = []                       # said once everything has opened (bad input stays one line)
    model, chain = load_chain(args.model, args.keys, args.rig, poses=args.poses, calibration=args.calibration,
                              options=SolveOptions(gaze=args.gaze, landmarks=args.landmarks), say=notes.append)
    from keyshape.base.formats.keys import check_keys_model
    from keyshape.tracker.commands import model_fingerprint
    check_keys_model(args.keys, model_fingerprint(model), False, "the live model")
    sender = LiveLinkSender(args.host, args.port, subject=args.subject)
    osc = None
    try:
        if osc_addr is not None:
            osc = OscSender(*osc_addr)
        source = FrameSource(args.source, pace=not args.no_pace)
        for line in notes:
            print(line, file=sys.stderr)
        print(f"keyshape live: {source.name} ({source.info.width}x{source.info.height} at {source.info.fps:g} fps) "
              f"-> Live Link Face {sender.target} subject {args.subject!r}"
              f"{f', OSC {args.osc}' if args.osc else ''}; {len(chain.rig_names)} rig curves; Ctrl-C stops",
              file=sys.stderr)
        stats = stream(source, model, chain, sender, osc)
    finally:
        sender.close()
        if osc is not None:
            osc.close()
    if stats.frames == 0:
        raise InputError(f"no frame came from {args.source}")
    return 0
