#!/usr/bin/env bash
# Install what the labelling page's browser test needs: Debian's chromium (driven by the
# Python playwright package, which must never download its own browsers).
# Usage: .ci/setup_browser.sh [PYTHON]   (PYTHON: the interpreter of the test venv)
set -euo pipefail
if ! command -v chromium >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -q
    $SUDO apt-get install -y -q chromium
fi
PY=${1:-python3}
if ! "$PY" -c "import playwright" >/dev/null 2>&1; then
    PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1 "$PY" -m pip install -q playwright
fi
echo "browser test setup: $(command -v chromium), playwright $("$PY" -c 'import importlib.metadata as m; print(m.version("playwright"))')"
