"""Command-line registration for dense-mesh tools (stub: filled in by the registration/key-point issue)."""
from __future__ import annotations


def register(subparsers) -> None:
    """Add this stage's subcommands to ``subparsers``."""
