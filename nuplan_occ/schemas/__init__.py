"""The on-disk contract: JSON Schemas and the label map, shipped as package data."""

from __future__ import annotations

import json
from functools import lru_cache
from importlib import resources


@lru_cache(maxsize=None)
def load(name: str) -> dict:
    """Load `schemas/<name>.json` (e.g. "labels", "frame_meta")."""
    return json.loads(resources.files(__name__).joinpath(f"{name}.json").read_text())
