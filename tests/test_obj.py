import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from keyshape.base.errors import InputError
from keyshape.base.formats.obj import read_obj, read_obj_vertices, write_obj

QUAD = """v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 2 0 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
g skin
f 1/1 2/2 3/3 4/4
g lip
f 2 5 3
"""


def test_obj_round_trip(tmp_path):
    (tmp_path / "a.obj").write_text(QUAD)
    m = read_obj(tmp_path / "a.obj")
    assert m.n_vertices == 5 and len(m.polygons) == 2
    assert m.triangles.tolist() == [[0, 1, 2], [0, 2, 3], [1, 4, 2]]
    assert m.group_vertices("lip").tolist() == [1, 2, 4]
    moved = m.vertices + 1.5
    write_obj(tmp_path / "b.obj", m, moved)
    m2 = read_obj(tmp_path / "b.obj")
    np.testing.assert_allclose(m2.vertices, moved)
    assert [p.tolist() for p in m2.polygons] == [p.tolist() for p in m.polygons]
    assert m2.polygon_uvs[0].tolist() == [0, 1, 2, 3] and m2.polygon_uvs[1] is None
    assert set(m2.groups) == {"skin", "lip"}
    np.testing.assert_allclose(read_obj_vertices(tmp_path / "b.obj", 5), moved)


@pytest.mark.parametrize("bad,match", [
    ("v 0 0\n", r"line 1: broken vertex line 'v 0 0'"),
    ("v 0 0 0\nv 1 x 0\n", r"line 2: broken vertex line"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", r"line 4: face names a vertex outside 1..3"),
    ("v 0 0 0\nv 1 0 0\nf 1 2\n", r"line 3: face with 2 vertices"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 a 3\n", r"line 4: broken face line"),
    ("# nothing\n", r"no vertices"),
])
def test_broken_obj(tmp_path, bad, match):
    (tmp_path / "bad.obj").write_text(bad)
    with pytest.raises(InputError, match="bad.obj.*" + match):
        read_obj(tmp_path / "bad.obj")


def test_vertex_count_mismatch(tmp_path):
    (tmp_path / "a.obj").write_text(QUAD)
    with pytest.raises(InputError, match="a.obj: 5 vertices, expected 6"):
        read_obj_vertices(tmp_path / "a.obj", 6)


def test_ict_neutral(shared_data):
    m = read_obj(shared_data / "ict-facekit/generic_neutral_mesh.obj", require_faces=True)
    assert m.n_vertices == 26719 and len(m.polygons) == 26384
    assert m.triangles.shape[1] == 3


@settings(max_examples=50, deadline=None)
@given(st.lists(st.lists(st.integers(0, 30), min_size=0, max_size=8), min_size=0, max_size=40))
def test_triangles_fan_every_polygon_in_order(polys):
    """The vectorised fan triangulation equals the definition: for each polygon of 3 or more
    vertices, in file order, (p0, pk, pk+1) for k = 1 .. len - 2; smaller polygons give nothing."""
    from keyshape.base.formats.obj import Mesh

    polys = [np.asarray(p, np.intp) for p in polys]
    want = [(p[0], p[k], p[k + 1]) for p in polys if len(p) >= 3 for k in range(1, len(p) - 1)]
    got = Mesh(np.zeros((31, 3)), polys).triangles
    assert got.shape == (len(want), 3) and got.dtype == np.intp
    assert got.tolist() == [list(t) for t in want]
