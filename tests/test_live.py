"""``keyshape live``: a synthetic video played as the camera, the Live Link Face packets received on
127.0.0.1 with the decoder, every frame's curves against what ``solve --livelink`` writes offline (one solve, the
pose library over it in both); the head against ``retarget --tracks``; the face lost and found; OSC; Ctrl-C; bad
input (one-line errors, exit 2); the packet layout."""
from __future__ import annotations

import csv
import importlib.util
import json
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import sigint_as_a_terminal_gives_it

from keyshape.base.errors import InputError
from keyshape.base.formats.livelink import (CSV_NAMES, N_VALUES, PACKET_NAMES, csv_to_packet, decode_packet,
                                            encode_packet)
from keyshape.cli import main

REPO = Path(__file__).resolve().parents[1]
N_FRAMES = 60


def _toy_rig_module():
    spec = importlib.util.spec_from_file_location("trp", Path(__file__).parent / "test_rig_poses.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    """A synthetic 640x480 take: model, key set, toy rig with its pose library, and the offline chain's files
    (tracks, weights, ``solve --livelink`` CSVs without and with the pose library, ``retarget --livelink``)."""
    from keyshape.data_synth.video import synthesize
    d = tmp_path_factory.mktemp("live")
    out = synthesize(d / "synth", frames=N_FRAMES, seed=3, labels=12)
    shutil.copy(out["video"], d / "take.mp4")
    _add_nose(out["labels"])
    rig, lm = _toy_rig_module().write_toy_rig(d / "rig")
    shutil.copy(lm, d / "lm.json")
    steps = [["train", str(d / "take.mp4"), "--labels", str(out["labels"]), "-o", str(d / "model.npz")],
             ["track", str(d / "take.mp4"), "--model", str(d / "model.npz"), "-o", str(d / "t.csv"), "--quiet"],
             ["select", str(d / "t.csv"), "-k", "4", "-o", str(d / "k.json")],
             ["pose", str(d / "k.json"), "--rig", str(rig), "--landmarks", str(lm), "-o", str(d / "poses.json")],
             ["decompose", str(d / "t.csv"), "--keys", str(d / "k.json"), "--solver", "nnls", "-o", str(d / "w.csv")],
             ["solve", str(d / "t.csv"), "--keys", str(d / "k.json"), "--rig", str(rig), "--landmarks", str(lm),
              "--livelink", "-o", str(d / "sll.csv")],
             ["solve", str(d / "t.csv"), "--keys", str(d / "k.json"), "--rig", str(rig), "--landmarks", str(lm),
              "--poses", str(d / "poses.json"), "--weights", str(d / "w.csv"), "--livelink", "-o", str(d / "sllp.csv")],
             # the 3D head and the eye angles (the defaults), and the 2D head's roll alone
             ["retarget", str(d / "w.csv"), "--poses", str(d / "poses.json"), "--rig", str(rig), "--tracks",
              str(d / "t.csv"), "--landmarks", str(lm), "--livelink", "-o", str(d / "ll.csv")],
             ]
    for s in steps:
        assert main(s) == 0, s
    from keyshape import api                             # the 2D head: an option of the API, not of the command
    api.retarget(api.Weights.load(d / "w.csv"), options=api.RetargetOptions(head="rigid", gaze="none", landmarks=str(lm)),
                 poses=d / "poses.json", rig=rig, tracks=api.read_tracks(d / "t.csv")).export(d / "ll2d.csv", livelink=True)
    return d


def _add_nose(labels: Path) -> None:
    """Give the 2D take's labels contours48's five nose points (contours48+nose, as ``keyshape label`` makes
    them), placed between the eyes and the upper lip, so that the model tracks them, the tracks carry them in
    their own columns and the 3D head (offline and live alike) uses them."""
    from keyshape.base.formats.labels import read_labels, write_labels
    frames, shapes = read_labels(labels)
    eyes, lip = (shapes[:, 14] + shapes[:, 18]) / 2, shapes[:, 31]
    w = shapes[:, 22, 0] - shapes[:, 10, 0]
    at = lambda f, dx: eyes + f * (lip - eyes) + np.stack([dx * w, 0 * w], 1)   # noqa: E731
    nose = np.stack([at(0.05, 0), at(0.6, 0), at(0.75, -0.12), at(0.85, 0), at(0.75, 0.12)], 1)
    write_labels(labels, frames, np.concatenate([shapes, nose], 1))


def live_args(d: Path, source: str | None = None, *extra: str) -> list[str]:
    return ["live", source or str(d / "take.mp4"), "--model", str(d / "model.npz"), "--keys", str(d / "k.json"),
            "--rig", str(d / "rig"), "--landmarks", str(d / "lm.json"), *extra]


class Receiver:
    """A UDP socket on 127.0.0.1 collecting datagrams in a thread until :meth:`join`."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.data: list[bytes] = []
        self.first = threading.Event()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while True:
            try:
                self.data.append(self.sock.recv(65536))
                self.first.set()
            except socket.timeout:
                if self.stop.is_set():              # nothing more within 0.1 s after join was asked
                    return
            except OSError:
                return

    def join(self):
        time.sleep(0.2)
        self.stop.set()
        self.thread.join(30)
        self.sock.close()
        return self.data


def read_livelink_csv(path) -> tuple[list[str], np.ndarray]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return rows[0][2:], np.array([[float(x) for x in r[2:]] for r in rows[1:]])


def _receive(take, *extra, source=None):
    rx = Receiver()
    assert main(live_args(take, source, "--port", str(rx.port), "--no-pace", *extra)) == 0
    packets = [decode_packet(p) for p in rx.join()]
    return packets, np.array([[p.named()[n] for n in CSV_NAMES] for p in packets])


def test_every_packet_equals_the_offline_solve(take, capsys):
    """One solve offline and live: live fits ``keyshape solve``'s solve once on the calibration (here the key set's
    own tracks, the take's) and solves each frame alone with it; ``solve --livelink`` on the same frames writes the
    same curves (to the head's temporal smoothing, which the mouth's yaw corrections read offline and live, which
    sees no future frame, goes without)."""
    packets, live = _receive(take, "--subject", "actor1")
    err = capsys.readouterr().err
    assert f"{N_FRAMES} frames" in err and "lost 0" in err and "latency" in err
    assert f"3D head and eye angles calibrated on {take / 't.csv'}" in err       # the key set's own tracks
    assert [p.frame for p in packets] == list(range(N_FRAMES))                  # every frame, in order
    assert {(p.subject, p.rate, p.version) for p in packets} == {("actor1", (30, 1), 6)}
    header, offline = read_livelink_csv(take / "sll.csv")
    assert header == CSV_NAMES
    assert np.abs(live[:, :52]).max() > 0.05                                     # the curves do move
    np.testing.assert_allclose(live[:, :52], offline[:, :52], rtol=0, atol=5e-3)

    # the same solve offline in memory with the head posed frame by frame, as live: equal to float32 precision
    import copy

    from keyshape import api
    from keyshape.decompose.take import Take
    from keyshape.retarget.api import fit_solve
    from keyshape.retarget.output.export import livelink_values
    from keyshape.retarget.rig.model import load_rig
    tracks = api.track(take / "take.mp4", api.AppearanceModel.load(take / "model.npz"))
    keys = api.Keys.load(take / "k.json")
    rig = load_rig(take / "rig", with_mesh=False)
    solve, *_ = fit_solve(Take.fit(api.read_tracks(take / "t.csv")), keys.regions, keys.scheme, keys.head_pose, rig,
                          api.SolveOptions(landmarks=str(take / "lm.json")))
    solve.estimator = copy.copy(solve.estimator)
    solve.estimator.smooth = 0.0
    curves = np.concatenate([solve.curves(tracks[i:i + 1]) for i in range(N_FRAMES)])
    mem = livelink_values(rig.names, curves).astype(np.float32)
    np.testing.assert_allclose(live[:, :52], mem[:, :52], rtol=0, atol=1e-6)
    np.testing.assert_allclose(curves, solve.curves_, rtol=0, atol=5e-3)       # the take's own solve


def test_the_pose_library_overrides_live_as_offline(take):
    """``--poses``: the artist's poses over the solve at their keys, as ``solve --poses --weights`` offline (the
    key weights of every frame by per-frame NNLS in both)."""
    _, live = _receive(take, "--poses", str(take / "poses.json"))
    _, offline = read_livelink_csv(take / "sllp.csv")
    _, plain = read_livelink_csv(take / "sll.csv")
    assert np.abs(offline[:, :52] - plain[:, :52]).max() > 0.02                 # the library does change the curves
    np.testing.assert_allclose(live[:, :52], offline[:, :52], rtol=0, atol=5e-3)


def test_head_and_eye_angles_equal_the_offline_ones(take):
    """The 3D head and the gaze: ``retarget --tracks`` fits the take's 3D head once (``Take.fit``), then calls
    ``head_from_tracks`` and
    ``gaze_from_tracks`` on the whole take; live fits the first once on the calibration (here the take's own
    tracks, the key set's) and applies the others to each frame alone with the 3D head's temporal smoothing
    off (offline's is a Gaussian over past and future frames). Offline with that smoothing off (and without the
    lids' pull on the pupils taken out, fitted on the whole take's blinks, and without the whole take's gaze
    denoising), every frame's 9 head and eye values are equal; the command's file differs by its smoothing,
    that pull and the denoising."""
    import copy

    from keyshape.base.formats.tracks import read_tracks
    from keyshape.decompose.take import Take
    from keyshape.retarget.api import gaze_from_tracks, head_from_tracks
    from keyshape.retarget.output.export import livelink_values
    from keyshape.retarget.rig.model import load_rig
    _, live = _receive(take)
    tr = read_tracks(take / "t.csv")
    assert tr.aux["nose"].shape == (N_FRAMES, 5, 2)                  # the model's nose: the 3D head's too
    causal = copy.copy(Take.fit(tr).head3d)
    causal.smooth = 0.0
    head = head_from_tracks(tr, tr.frame, None, 1.0, head=causal)
    eyes = gaze_from_tracks(tr, tr.frame, causal, lid_drag=False, denoise=False)   # live sees no future frame
    names = load_rig(take / "rig", with_mesh=False).names
    ref = livelink_values(names, np.zeros((N_FRAMES, len(names))), head, eyes)
    # float32 packets; live's points are the tracker's, the file's rounded to 1e-4 px (measured 3.8e-6 rad)
    np.testing.assert_allclose(live[:, 52:], ref[:, 52:], rtol=0, atol=2e-5)
    assert np.ptp(live[:, 52:55], axis=0).max() > 0.05 and np.ptp(live[:, [55, 58]], axis=0).min() > 0.1
    assert not live[:, [57, 60]].any()                                            # no eye roll
    # the command's own file (the head smoothed over time with sigma 1 frame): measured 0.0085 rad at most
    _, offline = read_livelink_csv(take / "ll.csv")
    np.testing.assert_allclose(live[:, 52:], offline[:, 52:], rtol=0, atol=0.02)


def test_2d_head_sends_the_roll_only(take):
    """``load_chain(head="2d")`` (the Python API; ``bench/bench_live.py`` measures it): the head's roll alone."""
    from keyshape.live import FrameSource, LiveLinkSender, load_chain, stream
    model, chain = load_chain(take / "model.npz", take / "k.json", [str(take / "rig")], head="2d",
                              options=_options(take), say=lambda line: None)
    rx = Receiver()
    sender = LiveLinkSender("127.0.0.1", rx.port)
    try:
        stream(FrameSource(str(take / "take.mp4"), pace=False), model, chain, sender, status=None)
    finally:
        sender.close()
    live = np.array([[p.named()[n] for n in CSV_NAMES] for p in (decode_packet(q) for q in rx.join())])
    _, offline = read_livelink_csv(take / "ll2d.csv")
    _, curves = read_livelink_csv(take / "sll.csv")
    np.testing.assert_allclose(live[:, :52], curves[:, :52], rtol=0, atol=5e-3)
    # the head roll: live stabilises on the key set's rigid reference, retarget on the take's own one
    np.testing.assert_allclose(live[:, 54], offline[:, 54], atol=2e-3)
    assert np.ptp(live[:, 54]) > 0.01 and not live[:, [52, 53, 55, 56, 57, 58, 59, 60]].any()


def _options(take):
    from keyshape.retarget.defaults import SolveOptions
    return SolveOptions(landmarks=str(take / "lm.json"))


def test_calibration_missing_is_one_line(take, tmp_path, capsys):
    """Live solves with a calibration take's statistics: without one (the key set's tracks gone, no
    --calibration) it says so in one line before any work."""
    import json
    keys = json.loads((take / "k.json").read_text())
    keys["source"]["tracks"] = [str(tmp_path / "gone.csv")]
    (tmp_path / "k.json").write_text(json.dumps(keys))
    assert main(live_args(take, None, "--no-pace", "--keys", str(tmp_path / "k.json"))) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gone.csv is gone" in err[0] and "--calibration" in err[0], err


def test_face_lost_sends_the_neutral_and_found_resumes(take, tmp_path, capsys):
    from keyshape.base.formats.video import VideoReader, video_writer
    frames = [f for _, f in VideoReader(take / "take.mp4")]
    with video_writer(tmp_path / "gap.mp4", 30.0, (640, 480)) as wr:
        for i, f in enumerate(frames):
            wr.write(np.full_like(f, 90) if 20 <= i < 30 else f)                  # no face in frames 20-29
    rx = Receiver()
    assert main(live_args(take, str(tmp_path / "gap.mp4"), "--port", str(rx.port), "--no-pace")) == 0
    packets = [decode_packet(p) for p in rx.join()]
    err = capsys.readouterr().err
    assert len(packets) == N_FRAMES
    neutral = [p.frame for p in packets if not np.any(p.values)]
    assert 20 in neutral and set(neutral) <= set(range(20, 32)), neutral
    assert "face lost at frame 20" in err and "face found again at frame" in err
    assert np.any(packets[-1].values)


def test_osc_one_message_per_rig_curve(take, capsys):
    pytest.importorskip("pythonosc", reason="python-osc not installed (pip install 'keyshape[osc]')")
    from pythonosc.osc_message import OscMessage
    from keyshape.retarget.rig.model import load_rig
    names = load_rig(take / "rig", with_mesh=False).names
    ll, osc = Receiver(), Receiver()
    assert main(live_args(take, None, "--port", str(ll.port), "--osc", f"127.0.0.1:{osc.port}", "--no-pace")) == 0
    packets = ll.join()
    msgs = [OscMessage(m) for m in osc.join()]
    assert len(packets) == N_FRAMES and len(msgs) == N_FRAMES * len(names)
    assert [m.address for m in msgs[:len(names)]] == [f"/keyshape/{n}" for n in names]
    assert all(len(m.params) == 1 and 0.0 <= m.params[0] <= 1.0 for m in msgs)


def test_ctrl_c_stops_cleanly_with_exit_130(take):
    rx = Receiver()
    proc = subprocess.Popen([sys.executable, "-m", "keyshape", *live_args(take, None, "--port", str(rx.port))],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                            preexec_fn=sigint_as_a_terminal_gives_it)
    try:
        assert rx.first.wait(60), "no packet arrived"
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()          # reaped, pipes closed: nothing spills into later tests
    assert proc.returncode == 130, err
    assert "frames" in err and "interrupted" in err and "Traceback" not in err
    assert 0 < len(rx.join()) < N_FRAMES                                         # paced: stopped part way


@pytest.mark.parametrize("case", ["host", "broadcast", "camera", "scheme", "osc", "osc_missing",
                                  "calibration", "calibration_scheme", "calibration_model", "poses_elsewhere",
                                  "foreign_keys", "huge_camera"])
def test_bad_input_is_one_line_and_exit_2(take, tmp_path, capsys, monkeypatch, case):
    extra: list[str] = ["--no-pace"]
    source = None
    if case == "host":
        extra += ["--host", "no-such-host.invalid"]
        want = "cannot resolve host"
    elif case == "broadcast":
        extra += ["--host", "255.255.255.255"]
        want = "unreachable"
    elif case == "camera":
        source = "57"
        want = "camera 57: cannot open"
    elif case == "scheme":
        from keyshape.base.formats.model import read_model, write_model
        from keyshape.base.schemes import load_scheme
        mf = read_model(take / "model.npz")
        mf.scheme = load_scheme("ibug68")
        write_model(tmp_path / "m68.npz", mf)
        extra += ["--model", str(tmp_path / "m68.npz")]
        want = "scheme 'ibug68'"
    elif case == "calibration":
        extra += ["--calibration", str(tmp_path / "none.csv")]
        want = "none.csv"
    elif case == "calibration_scheme":
        from keyshape.base.formats.tracks import read_tracks, write_tracks
        tr = read_tracks(take / "t.csv")
        tr.points, tr.meta = tr.points[:, :40], {}
        write_tracks(tmp_path / "t40.csv", tr)
        extra += ["--calibration", str(tmp_path / "t40.csv")]
        want = "40 points"
    elif case == "poses_elsewhere":                                   # the keys' frames are not the calibration's
        from keyshape.base.formats.tracks import read_tracks, write_tracks
        write_tracks(tmp_path / "late.csv", read_tracks(take / "t.csv")[N_FRAMES // 2:])
        extra += ["--calibration", str(tmp_path / "late.csv"), "--poses", str(take / "poses.json")]
        want = "not frames of the calibration"
    elif case == "calibration_model":
        from keyshape.base.formats.tracks import read_tracks, write_tracks
        tr = read_tracks(take / "t.csv")
        tr.meta = {**tr.meta, "model": "sha256:0123456789abcdef"}
        write_tracks(tmp_path / "other.csv", tr)
        extra += ["--calibration", str(tmp_path / "other.csv")]
        want = "another tracker model"
    elif case == "foreign_keys":                       # issue 37: as decompose and solve refuse them
        keys = json.loads((take / "k.json").read_text())
        keys.setdefault("source", {})["model"] = "sha256:0123456789abcdef"
        (tmp_path / "fk.json").write_text(json.dumps(keys))
        extra += ["--keys", str(tmp_path / "fk.json")]
        want = "another tracker model"
    elif case == "huge_camera":
        source = "99999999999999999999"
        want = "camera 99999999999999999999"
    elif case == "osc":
        extra += ["--osc", "127.0.0.1"]
        want = "HOST:PORT"
    else:
        monkeypatch.setitem(sys.modules, "pythonosc", None)
        monkeypatch.setitem(sys.modules, "pythonosc.udp_client", None)
        extra += ["--osc", "127.0.0.1:9000"]
        want = "keyshape[osc]"
    assert main(live_args(take, source) + extra) == 2              # a later --model wins in argparse
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and want in err[0], err


def test_packet_layout_and_decoder():
    vals = np.linspace(-1, 1, N_VALUES).astype(np.float32)
    pkt = encode_packet(vals, 1234, 29.97, subject="Anna", device_id="dev-1", subframe=0.25)
    # byte by byte, as Unreal's Live Link Face source reads it (big-endian)
    assert pkt[0] == 6
    assert struct.unpack(">i", pkt[1:5]) == (5,) and pkt[5:10] == b"dev-1"
    assert struct.unpack(">i", pkt[10:14]) == (4,) and pkt[14:18] == b"Anna"
    assert struct.unpack(">ifiiB", pkt[18:35]) == (1234, 0.25, 30000, 1001, 61)
    assert len(pkt) == 35 + 4 * 61
    np.testing.assert_array_equal(np.frombuffer(pkt[35:], ">f4"), vals)
    p = decode_packet(pkt)
    assert (p.subject, p.device_id, p.frame, p.subframe, p.rate) == ("Anna", "dev-1", 1234, 0.25, (30000, 1001))
    np.testing.assert_array_equal(p.values, vals)
    # the CSV's order differs from the packet's (Unreal's EARFaceBlendShape) for the jaw and mouth sides
    csv_vals = np.arange(N_VALUES, dtype=float)
    named = dict(zip(PACKET_NAMES, csv_to_packet(csv_vals)))
    assert named["JawRight"] == CSV_NAMES.index("JawRight") and named["MouthLeft"] == CSV_NAMES.index("MouthLeft")
    assert PACKET_NAMES.index("JawLeft") == 15 and PACKET_NAMES.index("HeadRoll") == 54
    for bad in (pkt[:-1], b"\x05" + pkt[1:], pkt + b"\0"):
        with pytest.raises(InputError):
            decode_packet(bad)


def test_a_frame_without_a_head_pose_holds_the_last_one(take):
    """A frame the 3D head finds no pose for (none seen: forced here) keeps the last frame's head, as offline
    holds failed frames, instead of stopping the stream."""
    import warnings

    from keyshape.base.formats.tracks import Tracks, read_tracks
    from keyshape.live import load_chain
    _, chain = load_chain(take / "model.npz", take / "k.json", [str(take / "rig")], options=_options(take),
                          say=lambda line: None)
    tr = read_tracks(take / "t.csv")
    one = [Tracks(tr.frame[i:i + 1], tr.time[i:i + 1], tr.confidence[i:i + 1], tr.success[i:i + 1],
                  tr.points[i:i + 1], tr.pose[i:i + 1], {}, {k: v[i:i + 1] for k, v in tr.aux.items()})
           for i in (5, 6)]
    first, _ = chain.head.frame(one[0])
    chain.head.estimator.camera_pose = lambda p: (np.full((len(p), 3, 3), np.nan), np.full((len(p), 3), np.nan))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)              # numpy on an all-NaN pose
        held, eyes = chain.head.frame(one[1])
    np.testing.assert_array_equal(held.angles, first.angles)
    assert np.isfinite(first.angles).all() and np.abs(first.angles).max() > 0
