"""Comments explain the code, figures live in one place (docs/benchmarks.md), history in CHANGELOG.md:
counted here so that it stays true.

- README.md and docs/ describe the system as it is: no "round N", "this round", "last round" or
  "previous round", and no issue numbers in section titles;
- README.md at most 180 lines, its "How good is it" one table and at most five sentences;
- no before-and-after figure (``0.92 -> 0.88``, ``from 0.92 to 0.88``) in the package's code comments
  and docstrings, in the folders listed in :data:`CLEAN` (the others still hold some: extend it as
  they are cleaned).
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
#: folders whose Python files hold no before-and-after figures
CLEAN = ["decompose", "data_synth", "keyshape", "bench", "retarget", "tracker"]

HISTORY = re.compile(r"\bround[- ]?\d+|\b(this|last|previous)\s+round\b", re.I)
ISSUE_TITLE = re.compile(r"^#+ .*\bissues? \d+", re.I | re.M)
FIGURE = re.compile(r"\d\.\d+(?:\s*/\s*\d\.\d+)*\s*(?:->|→)\s*-?\d+\.\d+"
                    r"|\bfrom -?\d+\.\d+(?:\s*/\s*\d\.\d+)* to -?\d+\.\d+")


@pytest.mark.parametrize("path", DOCS, ids=lambda p: p.name)
def test_docs_describe_the_system_as_it_is(path):
    text = path.read_text()
    found = [m.group(0) for m in HISTORY.finditer(text)]
    assert not found, f"{path.name}: round history {found[:5]} (history belongs in CHANGELOG.md)"
    titles = ISSUE_TITLE.findall(text) and [ln for ln in text.splitlines() if ISSUE_TITLE.match(ln)]
    assert not titles, f"{path.name}: issue numbers in section titles {titles[:3]}"


def _section(text: str, title: str) -> str:
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end > 0 else None]


def test_readme_is_short_and_its_figures_are_one_table():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 180, len(text.splitlines())
    body = _section(text, "How good is it").splitlines()[1:]
    tables = sum(1 for i, ln in enumerate(body) if ln.startswith("|") and not (i and body[i - 1].startswith("|")))
    assert tables == 1, tables
    prose = " ".join(ln for ln in body if not ln.startswith("|") and not ln.startswith("#"))
    prose = re.sub(r"`[^`]*`|\([^()]*\)|\[[^\]]*\]", "", prose)    # code, parentheses and links hold no sentence end
    sentences = re.findall(r"[.!?](?=\s|$)", prose)
    assert len(sentences) <= 5, (len(sentences), prose)


def _python_files():
    for folder in CLEAN:
        yield from sorted((REPO / folder).rglob("*.py"))


def test_no_before_and_after_figures_in_code_comments():
    bad = []
    for path in _python_files():
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if FIGURE.search(line):
                bad.append(f"{path.relative_to(REPO)}:{n}: {line.strip()[:80]}")
    assert not bad, "before-and-after figures belong in docs/benchmarks.md:\n" + "\n".join(bad[:10])


def test_the_checks_catch_what_they_are_for():
    assert HISTORY.search("measured this round") and HISTORY.search("Round 32 (speed)")
    assert HISTORY.search("the round-33 model") and not HISTORY.search("a round trip, three robust rounds")
    assert ISSUE_TITLE.search("### The lips (issue 13, second round)\n") and not ISSUE_TITLE.search("see issue 13\n")
    assert FIGURE.search("eye closure r 0.92 -> 0.88") and FIGURE.search("went from 0.868 to 0.906")
    assert FIGURE.search("r 0.80/0.83 -> 0.94/0.89") and not FIGURE.search("``-1 -> 1`` (OpenCV's border)")
