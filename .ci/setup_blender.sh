#!/usr/bin/env bash
# Install Debian's blender (3.4) for tests/test_blender.py: the rig .glb and the curves script
# opened in Blender itself. Its glTF importer needs numpy, which the test hands it from the venv.
set -euo pipefail
if ! command -v blender >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -q
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends blender
fi
echo "blender test setup: $(blender --version 2>/dev/null | head -1)"
