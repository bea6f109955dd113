"""CI cannot turn a missing optional tool into skips: .ci/run installs them without fallbacks and sets
KEYSHAPE_REQUIRE_OPTIONAL=1, under which tests/conftest.py fails such a skip."""
from pathlib import Path

from conftest import optional_skip_is_failure

CI = Path(__file__).resolve().parents[1] / ".ci" / "run"


def test_ci_requires_the_optional_tools():
    text = CI.read_text()
    assert "export KEYSHAPE_REQUIRE_OPTIONAL=1" in text
    code = [line.split("#")[0] for line in text.splitlines()]
    assert not [line for line in code if "|| echo" in line or "|| true" in line]


def test_optional_skip_becomes_a_failure_only_when_required():
    on, off = {"KEYSHAPE_REQUIRE_OPTIONAL": "1"}, {}
    for reason in ("dlib (keyshape[label]) not installed", "playwright not installed",
                   "Khronos gltf-validator not installed"):
        assert optional_skip_is_failure(reason, on) and not optional_skip_is_failure(reason, off)
    assert not optional_skip_is_failure("real data not found at ../shared/data", on)
