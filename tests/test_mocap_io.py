"""Marker files: C3D/TRC/CSV readers on real files, round trips, gaps as NaN, bad input."""
from __future__ import annotations

import numpy as np
import pytest

from keyshape.base.errors import InputError, MissingFileError
from keyshape.base.formats.markers import Markers, read_c3d, read_markers, read_trc, unit_scale, write_markers


def _take(rng, n_frames=20, n_markers=5):
    p = rng.normal(0, 100, (n_frames, n_markers, 3))
    p[3:6, 1] = np.nan
    return Markers(p, [f"m{i}" for i in range(n_markers)], 120.0, "mm")


def test_real_c3d(shared_data):
    m = read_c3d(shared_data / "mocap/pyomeca/markers_analogs.c3d")
    assert m.positions.shape == (580, 51, 3)
    assert (m.rate, m.units) == (100.0, "mm")
    assert m.labels[0] == "boite:gauche_ext" and len(set(m.labels)) == 51
    gaps = ~np.isfinite(m.positions).all(axis=2)
    assert gaps.sum() == 305                     # the file's negative residuals
    assert not np.any(np.all(m.positions == 0, axis=2))   # gaps are NaN, never zeros


def test_real_trc_files(shared_data):
    m = read_trc(shared_data / "mocap/pyomeca/markers.trc")     # comma-separated, header says 652 frames
    assert m.positions.shape == (93, 51, 3)                     # the data rows win over the header,
    assert "header announces 652 frames but the file holds 93" in m.warnings[0]   # with a warning
    assert m.labels[:3] == ["ASISl", "ASISr", "PSISl"] and m.rate == 100.0
    np.testing.assert_allclose(m.positions[0, 0], [733.7041, 80.9832, 191.8668])
    a = read_trc(shared_data / "mocap/animface/jaw.trc")        # tab-separated
    assert a.positions.shape == (1590, 41, 3) and a.rate == 60.0 and a.units == "mm"
    assert a.labels[0] == "ForeHead_M" and a.labels[-1] == "Chin_L2"
    assert np.isfinite(a.positions).all()


@pytest.mark.parametrize("ext", [".trc", ".csv", ".c3d"])
def test_round_trip_keeps_gaps_labels_rate(tmp_path, ext):
    m = _take(np.random.default_rng(0))
    write_markers(tmp_path / f"t{ext}", m)
    r = read_markers(tmp_path / f"t{ext}")
    assert r.labels == m.labels and r.rate == 120.0 and r.units == "mm"
    np.testing.assert_allclose(r.positions, m.positions, atol=1e-5 if ext != ".c3d" else 1e-3, equal_nan=True)
    assert np.isnan(r.positions[3:6, 1]).all()
    assert not list(tmp_path.glob(".*partial*"))  # atomic: no temporary left behind


def test_c3d_labels2_missing_and_duplicate_labels(tmp_path):
    import ezc3d

    rng = np.random.default_rng(1)
    n = 6
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [200.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = ["a", "b", "c"]
    c.add_parameter("POINT", "LABELS2", ["d", "", " "])       # spill-over; the 5th and 6th empty
    p = np.ones((4, n, 10))
    p[:3] = rng.normal(size=(3, n, 10))
    p[:3, 2, 4] = 0.0                                          # a gap written as zeros
    c["data"]["points"] = p
    c.write(str(tmp_path / "x.c3d"))
    m = read_c3d(tmp_path / "x.c3d")
    assert m.labels == ["a", "b", "c", "d", "M005", "M006"]
    assert m.rate == 200.0
    assert np.isnan(m.positions[4, 2]).all()
    c["parameters"]["POINT"]["LABELS"]["value"] = ["a", "b", "a"]
    c.write(str(tmp_path / "dup.c3d"))
    with pytest.raises(InputError, match=r"dup\.c3d: duplicate marker labels \['a'\]"):
        read_c3d(tmp_path / "dup.c3d")
    assert read_c3d(tmp_path / "dup.c3d", duplicates="rename").labels[:3] == ["a", "b", "a#2"]


def test_bad_files(tmp_path):
    with pytest.raises(MissingFileError, match="nope.trc"):
        read_trc(tmp_path / "nope.trc")
    (tmp_path / "bad.trc").write_text("hello\n")
    with pytest.raises(InputError, match="bad.trc.*PathFileType"):
        read_trc(tmp_path / "bad.trc")
    (tmp_path / "bad.c3d").write_bytes(b"\x00" * 64)
    with pytest.raises(InputError, match="bad.c3d"):
        read_c3d(tmp_path / "bad.c3d")
    with pytest.raises(InputError, match="unknown marker format"):
        read_markers(tmp_path / "x.bvh")
    m = _take(np.random.default_rng(2))
    write_markers(tmp_path / "ok.trc", m)
    text = (tmp_path / "ok.trc").read_text().splitlines()
    text[7] = text[7].replace("\t", "\tabc", 1)
    (tmp_path / "broken.trc").write_text("\n".join(text))
    with pytest.raises(InputError, match="broken.trc, line 8"):
        read_trc(tmp_path / "broken.trc")
    with pytest.raises(InputError, match="unknown marker label"):
        m.index(["m1", "zz"])
    assert unit_scale("mm", "cm") == pytest.approx(0.1)


def test_trc_missing_labels_and_csv_rate_from_time(tmp_path):
    m = _take(np.random.default_rng(3), n_markers=3)
    write_markers(tmp_path / "a.trc", m)
    lines = (tmp_path / "a.trc").read_text().splitlines()
    lines[3] = "Frame#\tTime\tm0\t\t\t\t\t\tm2"             # the second label is missing
    (tmp_path / "b.trc").write_text("\n".join(lines) + "\n")
    assert read_trc(tmp_path / "b.trc").labels == ["m0", "M002", "m2"]   # by column; the missing one numbered
    write_markers(tmp_path / "a.csv", m)
    body = [ln for ln in (tmp_path / "a.csv").read_text().splitlines() if not ln.startswith("#")]
    (tmp_path / "b.csv").write_text("\n".join(body) + "\n")
    r = read_markers(tmp_path / "b.csv")
    assert r.rate == pytest.approx(120.0, rel=1e-4) and r.units == "mm"
