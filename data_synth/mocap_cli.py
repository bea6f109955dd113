"""Command-line registration for this stage (stub: filled in by the issue that builds it)."""
from __future__ import annotations


def register(subparsers) -> None:
    """Add this stage's subcommands to ``subparsers``."""
