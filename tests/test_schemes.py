import json

import numpy as np
import pytest

from keyshape.base.errors import InputError, MissingFileError
from keyshape.base.schemes import BUILTIN, load_scheme, scheme_for_n_points


@pytest.mark.parametrize("name,n,io", [("contours48", 48, (10, 22)), ("ibug68", 68, (36, 45))])
def test_builtin_integrity(name, n, io):
    s = load_scheme(name)
    assert s.n_points == n and s.inter_ocular == io
    covered = sorted(i for idx in s.contours.values() for i in idx)
    assert covered == list(range(n)), "contours cover every point exactly once"
    in_regions = sorted(i for idx in s.regions.values() for i in idx)
    assert in_regions == list(range(n)), "regions partition the points"


def test_contours48_layout():
    s = load_scheme("contours48")
    assert s.contours["brow_left"] == tuple(range(0, 5))
    assert s.contours["eye_left"] == tuple(range(10, 18))
    assert s.contours["eye_right"] == tuple(range(18, 26))
    assert s.contours["pupil_left"] == (26,) and s.contours["pupil_right"] == (27,)
    assert s.contours["lip_outer"] == tuple(range(28, 40))
    assert s.contours["lip_inner"] == tuple(range(40, 48))
    assert set(s.regions) == {"brows", "eyes", "pupils", "mouth"}
    # outer corners: start of the image-left eye, image-right corner of the image-right eye
    assert s.inter_ocular == (s.contours["eye_left"][0], s.contours["eye_right"][4])


def test_ibug68_groups():
    s = load_scheme("ibug68")
    assert s.regions["jaw"] == tuple(range(17))
    assert s.regions["mouth"] == tuple(range(48, 68))
    assert s.contours["lip_inner"] == tuple(range(60, 68))


def test_region_union_and_unknown():
    s = load_scheme("contours48")
    assert len(s.region("eyes+brows")) == 26
    with pytest.raises(InputError, match="no region 'jaw'"):
        s.region("jaw")


def test_interocular_distance():
    s = load_scheme("contours48")
    shapes = np.zeros((3, 48, 2))
    shapes[:, 22, 0] = [10, 20, 30]
    np.testing.assert_allclose(s.interocular_distance(shapes), [10, 20, 30])
    with pytest.raises(InputError, match=r"expected shape \(\.\.\., 48, 2\)"):
        s.check_shapes(np.zeros((3, 47, 2)))


def test_scheme_file_and_errors(tmp_path):
    from pathlib import Path

    data = json.loads(Path(load_scheme("ibug68").source).read_text())
    data["regions"]["mouth"].append(99)
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"bad\.json: region 'mouth' names points \[99\]"):
        load_scheme(p)
    with pytest.raises(MissingFileError):
        load_scheme(tmp_path / "none.json")
    with pytest.raises(InputError, match="unknown landmark scheme 'foo'"):
        load_scheme("foo")
    (tmp_path / "garbage.json").write_text("{not json")
    with pytest.raises(InputError, match="garbage.json: not valid JSON"):
        load_scheme(tmp_path / "garbage.json")


def test_scheme_for_n_points():
    assert scheme_for_n_points(68).name == "ibug68"
    with pytest.raises(InputError, match="no built-in landmark scheme has 5 points"):
        scheme_for_n_points(5)
    assert set(BUILTIN) == {"contours48", "ibug68"}


def test_contours48_nose_is_an_auxiliary_group():
    """contours48's auxiliary nose (iBUG-68 27, 30, 31, 33, 35) is not among its 48 points; its full form
    appends it (contours48+nose, 53 points, a 'nose' contour and region), loads by name, travels in a
    model file's scheme dict and splits back; its 3D face is the ibug68 template's nose with its weights."""
    from keyshape.base.schemes import load_head_template, scheme_from_dict, scheme_to_dict
    s = load_scheme("contours48")
    assert s.n_points == s.core == 48 and s.auxiliary == {"nose": (27, 30, 31, 33, 35)}
    f = s.full()
    assert (f.name, f.n_points, f.core, f.base_name) == ("contours48+nose", 53, 48, "contours48")
    assert f.contours["nose"] == f.regions["nose"] == (48, 49, 50, 51, 52) and f.rigid == s.rigid
    assert f.full() is f and load_scheme("contours48+nose") == f
    assert scheme_from_dict(scheme_to_dict(f), "x") == f and scheme_from_dict(scheme_to_dict(s), "x") == s
    pts = np.arange(53 * 2, dtype=float).reshape(53, 2)
    core, aux = f.split(pts)
    assert core.shape == (48, 2) and np.array_equal(aux["nose"], pts[48:])
    X, w = load_head_template(f)
    X68, w68 = load_head_template("ibug68")
    X48, _ = load_head_template(s)
    assert np.array_equal(X[:48], X48) and np.array_equal(X[48:], X68[[27, 30, 31, 33, 35]])
    assert np.array_equal(w[48:], w68[[27, 30, 31, 33, 35]]) and (w[48:] > 0).all()
    with pytest.raises(InputError, match="auxiliary points nose"):
        load_scheme("contours48+ears")
    bad = {**scheme_to_dict(s), "auxiliary": {"nose": {"ibug68": [27, 70]}}}
    with pytest.raises(InputError, match="auxiliary group 'nose'"):
        scheme_from_dict(bad, "bad.json")
    short = {**scheme_to_dict(f), "n_core": 47}
    with pytest.raises(InputError, match="n_core 47 and the auxiliary points do not add up to n_points 53"):
        scheme_from_dict(short, "short.json")
