"""The `nuplan-occ` command line: build and synthesis commands (app), dataset tools (dataset), release
import (release) and the one-line rendering of expected errors (errors)."""

from nuplan_occ.cli.app import app, main

__all__ = ["app", "main"]
