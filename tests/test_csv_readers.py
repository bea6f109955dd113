"""Every CSV keyshape writes opens in the standard readers with their defaults: the header on the
first line, numbers in the numeric columns (``csv.DictReader``, ``numpy.genfromtxt(names=True)``,
and ``pandas.read_csv`` where pandas is installed; keyshape does not depend on it)."""
from __future__ import annotations

import csv

import numpy as np
import pytest

from keyshape.base.formats.livelink import CSV_NAMES, N_VALUES, csv_rows
from keyshape.base.formats.markers import Markers, read_markers, write_markers
from keyshape.base.formats.tracks import Tracks, read_tracks, write_tracks
from keyshape.base.formats.weights import read_weights, read_weights_fps, write_weights
from keyshape.base.files import atomic_write
from keyshape.decompose.compare import COLUMNS, write_errors
from keyshape.retarget.rig.model import Rig
from keyshape.retarget.output.rig_export import export_rig

N = 6


def _weights(path):
    w = np.linspace(0, 1, N * 2).reshape(N, 2)
    write_weights(path, np.arange(N), ["mouth_0", "eyes_0"], w, np.array([0, 0, 1, 0, 0, 0]), fps=24.0)
    return ["frame", "time", "mouth_0", "eyes_0", "interpolated"]


def _curves(path):
    from keyshape.base.formats.obj import Mesh
    verts = np.random.default_rng(0).normal(size=(4, 3))
    rig = Rig(["jawOpen", "mouthSmile_L"], verts, np.zeros((2, 4, 3)), Mesh(verts, [np.array([0, 1, 2])]))
    export_rig(path, rig, np.arange(N), np.full((N, 2), 0.25), fps=24.0)
    return ["frame", "time", "jawOpen", "mouthSmile_L"]


def _livelink(path):
    header, rows = csv_rows(np.full((N, N_VALUES), 0.5), 24.0)
    with atomic_write(path, newline="") as f:
        wr = csv.writer(f)
        wr.writerow(header)
        wr.writerows(rows)
    return CSV_NAMES[:3]


def _tracks(path):
    pts = np.random.default_rng(1).uniform(0, 100, (N, 48, 2))
    tr = Tracks(np.arange(N), np.arange(N) / 24.0, np.ones(N), np.ones(N, bool), pts,
                np.tile([[1.0, 0, 0], [0, 1.0, 0]], (N, 1, 1)), meta={"scheme": "contours48"})
    write_tracks(path, tr)
    return ["frame", "time", "confidence", "success", "x_0", "y_47", "pose_ty"]


def _markers(path):
    pos = np.random.default_rng(2).normal(size=(N, 3, 3))
    write_markers(path, Markers(pos, ["a", "b", "c"], 120.0, "cm"))
    return ["frame", "time", "a_x", "c_z"]


def _errors(path):
    write_errors(path, [{"method": "spread", "region": "mouth", "k": 2, **{c: 0.5 for c in COLUMNS[3:]}}])
    return ["k", *COLUMNS[3:]]


WRITERS = {"weights": _weights, "curves": _curves, "livelink": _livelink, "tracks": _tracks,
           "markers": _markers, "compare errors": _errors}


@pytest.mark.parametrize("kind", list(WRITERS))
def test_dict_reader_and_numpy_read_every_csv_with_their_defaults(tmp_path, kind):
    path = tmp_path / "out.csv"
    numeric = WRITERS[kind](path)
    assert not path.read_text().startswith("#")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == (1 if kind == "compare errors" else N)
    for col in numeric:
        assert all(np.isfinite(float(r[col])) for r in rows), col
    a = np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")
    for col in numeric:
        assert np.isfinite(np.atleast_1d(a[col]).astype(float)).all(), col


def test_weights_frame_time_and_weights_read_as_numbers(tmp_path):
    path = tmp_path / "weights.csv"
    _weights(path)
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["frame"]) for r in rows] == list(range(N))
    np.testing.assert_allclose([float(r["time"]) for r in rows], np.arange(N) / 24.0, atol=1e-6)
    np.testing.assert_allclose([float(r["eyes_0"]) for r in rows], np.linspace(0, 1, 2 * N)[1::2], atol=1e-6)
    assert read_weights_fps(path) == 24.0 and read_weights(path).names == ["mouth_0", "eyes_0"]


@pytest.mark.parametrize("kind", ["weights", "curves", "tracks", "markers"])
def test_pandas_reads_frame_time_and_values_as_numbers(tmp_path, kind):
    pd = pytest.importorskip("pandas")
    path = tmp_path / "out.csv"
    numeric = WRITERS[kind](path)
    df = pd.read_csv(path)
    assert list(df.columns[:2]) == ["frame", "time"] and len(df) == N
    for col in numeric:
        assert pd.api.types.is_numeric_dtype(df[col]), col


def test_the_rate_and_units_of_a_marker_csv_survive_without_a_comment_line(tmp_path):
    """The marker CSV's rate and units travel in its sidecar; an older file's comment lines still read,
    and a CSV changed after its sidecar was written reads by its time column (with a warning)."""
    path = tmp_path / "take.csv"
    _markers(path)
    m = read_markers(path)
    assert (m.rate, m.units) == (120.0, "cm") and (tmp_path / "take.meta.json").is_file()
    old = tmp_path / "old.csv"
    old.write_text("# rate=60\n# units=m\n" + path.read_text())
    assert (read_markers(old).rate, read_markers(old).units) == (60.0, "m")
    path.write_text(path.read_text().replace("frame,time,", "frame,time, "))   # edited after the sidecar
    with pytest.warns(UserWarning, match="written for another version"):
        m = read_markers(path)
    assert (m.rate, m.units) == (120.0, "mm")


def test_tracks_sidecar_keeps_the_header_on_the_first_line(tmp_path):
    _tracks(tmp_path / "t.csv")
    assert (tmp_path / "t.csv").read_text().startswith("frame,time,confidence,success,x_0,")
    assert read_tracks(tmp_path / "t.csv").meta == {"scheme": "contours48"}
