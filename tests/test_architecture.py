"""The import rule (docs/architecture.md): every module imports only its own floor and the floors below.

Floors, bottom up::

    roof      keyshape.cli, keyshape.demo, keyshape.api, keyshape.batch  (may import everything)
    stage 4   keyshape.data_synth        (base + every stage)
    stage 3   keyshape.retarget          (base + tracker + decompose)
    stage 2   keyshape.decompose         (base + tracker)
    stage 1   keyshape.tracker           (base)
    base      keyshape.base              (nothing of keyshape above it)

Imports are read with :mod:`ast` from the source files (top-level and inside functions,
``TYPE_CHECKING`` blocks included), so a lazy import cannot hide an upward edge. Import cycles
between keyshape modules fail too, lazy imports included (two modules that import each other,
even inside functions, are one module in two files; a package's ``__init__`` importing its own
submodules is not counted).
"""
from __future__ import annotations

import ast
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# installed name -> folder in the repository (pyproject.toml's package-dir)
FOLDERS = {"keyshape.tracker": "tracker", "keyshape.decompose": "decompose", "keyshape.retarget": "retarget",
           "keyshape.data_synth": "data_synth", "keyshape": "keyshape"}
STAGES = ("base", "tracker", "decompose", "retarget", "data_synth")
# floor -> the floors it may import (its own included); everything in keyshape/ that is neither the
# base nor a stage (cli, demo, api, batch, __main__, the package's __init__) is the roof
FLOORS = {"base": {"base"},
          "tracker": {"base", "tracker"},
          "decompose": {"base", "tracker", "decompose"},
          "retarget": {"base", "tracker", "decompose", "retarget"},
          "data_synth": {"base", "tracker", "decompose", "retarget", "data_synth"},
          "roof": {"base", "tracker", "decompose", "retarget", "data_synth", "roof"}}


def floor(module: str) -> str | None:
    """The floor of a ``keyshape.X...`` module name; None outside keyshape and for the bare
    package name ``keyshape`` (importing any submodule loads it anyway)."""
    parts = module.split(".")
    if parts[0] != "keyshape" or len(parts) == 1:
        return None
    return parts[1] if parts[1] in STAGES else "roof"


def modules(root: Path = ROOT, folders: dict = FOLDERS) -> dict[str, Path]:
    """Installed module name -> source file, for every .py of the mapped folders."""
    out = {}
    for pkg, folder in folders.items():
        base = root / folder
        for f in sorted(base.rglob("*.py")):
            rel = f.relative_to(base).with_suffix("")
            if pkg == "keyshape" and rel.parts and rel.parts[0] in {"tracker", "decompose", "retarget", "data_synth"}:
                continue
            parts = [p for p in rel.parts if p != "__init__"]
            out[".".join([pkg, *parts])] = f
    return out


def imports(path: Path, name: str) -> list[tuple[str, int, bool]]:
    """(imported module, line, at module level) for every import in ``path`` (module ``name``)."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []

    def visit(node, top: bool):
        for child in ast.iter_child_nodes(node):
            inner = top and not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                out.extend((a.name, child.lineno, top) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")
                    base = base[:len(base) - child.level + 1]
                    mod = ".".join(base + ([child.module] if child.module else []))
                else:
                    mod = child.module or ""
                out.append((mod, child.lineno, top))
                for a in child.names:                    # ``from keyshape import retarget`` names a module
                    out.append((f"{mod}.{a.name}", child.lineno, top))
            visit(child, inner)

    visit(tree, True)
    return out


def check(root: Path = ROOT, folders: dict = FOLDERS) -> list[str]:
    """Every violation of the import rule under ``root``, as ``file:line: message`` strings."""
    mods = modules(root, folders)
    problems, graph, seen = [], {m: set() for m in mods}, set()
    for name, path in mods.items():
        here = floor(name) or "roof"   # the package's own __init__ (lazy API) is the roof
        for target, line, top in imports(path, name):
            there = floor(target)
            if there is None:
                continue
            where = f"{path.relative_to(root)}:{line}"
            real = target if target in mods else target.rpartition(".")[0]
            if there not in FLOORS[here] and (where, real) not in seen:
                seen.add((where, real))
                problems.append(f"{where}: {name} ({here}) imports {real} ({there}): upward import")
            if real in mods and real != name and not (mods[name].name == "__init__.py"
                                                      and real.startswith(name + ".")):
                graph[name].add(real)
    # module-level cycles (Tarjan's strongly connected components)
    index, low, stack, on, sccs, counter = {}, {}, [], set(), [], [0]

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            sccs.append(comp)

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10000))
    for v in graph:
        if v not in index:
            strong(v)
    for comp in sccs:
        # a package importing its own submodules (``__init__`` re-exports) is not a cycle of concern
        # when the submodule does not import the package back at module level
        if len(comp) > 1:
            problems.append(f"import cycle: {' -> '.join(sorted(comp))}")
    return problems


def test_the_namespace_commit_broke_the_rule(tmp_path):
    """What the checker reports on small copies of two real defects of the tree before issue 12:
    KEYS.json's reader in the base importing the decompose stage, and eigenpoints <-> model_io."""
    files = {"keyshape/__init__.py": "", "keyshape/base/__init__.py": "", "keyshape/base/formats/__init__.py": "",
             "keyshape/base/formats/keys.py": "from keyshape.decompose.regions import REGIONS, RegionKeys\n",
             "decompose/__init__.py": "", "decompose/regions.py": "import numpy\n",
             "tracker/__init__.py": "",
             "tracker/eigenpoints.py": "def save():\n    from keyshape.tracker.model_io import save_model\n",
             "tracker/model_io.py": "from keyshape.tracker.eigenpoints import AppearanceModel\n"}
    for rel, src in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(src)
    folders = {"keyshape.tracker": "tracker", "keyshape.decompose": "decompose", "keyshape": "keyshape"}
    assert check(tmp_path, folders) == [
        "keyshape/base/formats/keys.py:1: keyshape.base.formats.keys (base) imports keyshape.decompose.regions "
        "(decompose): upward import",
        "import cycle: keyshape.tracker.eigenpoints -> keyshape.tracker.model_io"]


def test_no_upward_or_circular_imports():
    problems = check()
    assert not problems, "import rule broken (docs/architecture.md):\n" + "\n".join(problems)


def test_every_module_is_seen():
    mods = modules()
    for m in ("keyshape.base.errors", "keyshape.base.formats.weights", "keyshape.tracker.eigenpoints",
              "keyshape.decompose.selectors", "keyshape.retarget.mocap.drive", "keyshape.data_synth.video",
              "keyshape.cli"):
        assert m in mods
    assert floor("keyshape.cli") == "roof" and floor("keyshape.base.formats.tracks") == "base"
    assert floor("keyshape.retarget.dense.io") == "retarget" and floor("numpy") is None


def _fake_tree(tmp_path: Path, files: dict) -> tuple[Path, dict]:
    for rel, src in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(textwrap.dedent(src))
    return tmp_path, {"keyshape.tracker": "tracker", "keyshape.retarget": "retarget", "keyshape": "keyshape"}


@pytest.mark.parametrize("upward", [
    "from keyshape.retarget.targets.blend import blend\n",                    # top level
    "def f():\n    from keyshape.retarget.targets.target_set import blend\n",            # inside a function
    "import keyshape.cli\n",                                          # a stage importing the roof
])
def test_checker_catches_an_upward_import(tmp_path, upward):
    """The checker run on a fake tree: a tracker module importing retarget (or the roof) is reported;
    the same tree without that import is clean."""
    files = {"keyshape/__init__.py": "", "keyshape/base/__init__.py": "", "keyshape/base/errors.py": "",
             "keyshape/cli.py": "import keyshape.retarget.targets.blend\n",
             "tracker/__init__.py": "", "tracker/fit.py": "from keyshape.base.errors import x\n",
             "retarget/__init__.py": "", "retarget/targets/blend.py": "from keyshape.tracker.fit import y\n"}
    root, folders = _fake_tree(tmp_path, files)
    assert check(root, folders) == []
    (root / "tracker" / "fit.py").write_text("from keyshape.base.errors import x\n" + upward)
    problems = check(root, folders)
    assert len(problems) >= 1 and "tracker/fit.py:" in problems[0] and "upward import" in problems[0]


def test_checker_catches_a_cycle(tmp_path):
    files = {"keyshape/__init__.py": "", "keyshape/base/__init__.py": "",
             "keyshape/base/a.py": "from keyshape.base import b\n", "keyshape/base/b.py": "import keyshape.base.a\n",
             "tracker/__init__.py": "", "retarget/__init__.py": ""}
    root, folders = _fake_tree(tmp_path, files)
    assert check(root, folders) == ["import cycle: keyshape.base.a -> keyshape.base.b"]
    (root / "keyshape/base/b.py").write_text("def f():\n    import keyshape.base.a\n")   # lazy: still a cycle
    assert check(root, folders) == ["import cycle: keyshape.base.a -> keyshape.base.b"]
    (root / "keyshape/base/b.py").write_text("import numpy\n")
    assert check(root, folders) == []
