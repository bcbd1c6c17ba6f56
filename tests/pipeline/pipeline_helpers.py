"""Build params for the end-to-end tests."""

from __future__ import annotations

from nuplan_occ.pipeline.params import apply_overrides, default_params

FAST_OVERRIDES = {"reconstruct": {"method": "poisson", "object_method": "poisson"}, "load": {"context_seconds": 0.25}}
"""The cheaper surface method and a shorter context for tests that build many times (resume, executors);
the defaults (the torch solver, 1 s of context) are exercised by test_build_end_to_end."""


def build_params(fast: bool = True) -> dict:
    from stages import PIPELINE

    params = default_params(PIPELINE)
    return apply_overrides(params, FAST_OVERRIDES, "tests") if fast else params
