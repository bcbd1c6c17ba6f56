"""Foreground-Background Separate Aggregation (FBSA) math: pure functions, no file I/O.

Modules: split (points in boxes, per-frame foreground/background split), outliers (statistical filters),
register (ICP refinement of logged ego poses), aggregate (background in the scene frame, objects in their
box frames), metrics (quality figures against synthetic truth).
"""

from __future__ import annotations


class FbsaInputError(ValueError):
    """Inputs of an FBSA function that do not fit together (shapes, frames, lengths); the message names the
    argument and the problem."""
