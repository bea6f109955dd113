import os
import stat

import pytest

from keyshape.base.files import atomic_dir, atomic_path, atomic_write


def test_atomic_write_mode_follows_umask(tmp_path):
    old = os.umask(0o022)
    try:
        with atomic_write(tmp_path / "a.txt") as f:
            f.write("x")
        with atomic_path(tmp_path / "b.bin") as p:
            p.write_bytes(b"x")
        with atomic_dir(tmp_path / "d") as d:
            (d / "f").write_text("x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "b.bin").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "d").stat().st_mode) == 0o755


def test_failed_writes_leave_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_write(tmp_path / "a.txt") as f:
            f.write("half")
            raise RuntimeError
    with pytest.raises(RuntimeError):
        with atomic_dir(tmp_path / "d") as d:
            (d / "f").write_text("x")
            raise RuntimeError
    (tmp_path / "keep").mkdir()
    (tmp_path / "keep" / "old").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_dir(tmp_path / "keep", overwrite=True) as d:
            raise RuntimeError
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep"]
    assert (tmp_path / "keep" / "old").read_text() == "old"


def test_a_folder_output_follows_the_running_commands_overwrite_and_inputs(tmp_path):
    """atomic_dir and check_output_dir given no overwrite or inputs take the running command's (its --overwrite
    and declared inputs), so a command does not thread them; given, they are used as they are."""
    from keyshape.base.errors import InputError
    from keyshape.base.files import Run, check_output_dir, run_rules

    out = tmp_path / "out"
    out.mkdir()
    (out / "user.txt").write_text("the user's")
    with run_rules(Run(overwrite=False)):
        with pytest.raises(InputError, match="not empty"):
            check_output_dir(out)
        with atomic_dir(out, True, kind="x") as d:                      # given: used as given
            (d / "a").write_text("a")
    with run_rules(Run(inputs=[out / "a"], overwrite=True)):
        check_output_dir(out)
        with pytest.raises(InputError, match="overwrite its input"):
            with atomic_dir(out, kind="x") as d:
                (d / "a").write_text("b")
        with atomic_dir(out, kind="x") as d:
            (d / "b").write_text("b")
    assert (out / "a").read_text() == "a" and (out / "b").read_text() == "b"
    assert (out / "user.txt").read_text() == "the user's"
