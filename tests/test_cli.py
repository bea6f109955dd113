import subprocess
import sys

from keyshape.cli import build_parser, main


def test_help_lists_commands():
    text = build_parser().format_help()
    assert "demo" in text and "synth" in text and "scheme" in text


def test_scheme_command(capsys):
    assert main(["scheme", "ibug68"]) == 0
    assert "68 points" in capsys.readouterr().out


def test_error_is_one_line_exit_2(tmp_path, capsys):
    rc = main(["scheme", str(tmp_path / "missing.json")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and "missing.json: landmark scheme not found" in err
    assert "Traceback" not in err


def test_module_entry_runs():
    r = subprocess.run([sys.executable, "-m", "keyshape", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "keyshape" in r.stdout
