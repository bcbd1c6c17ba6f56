"""Build params for the end-to-end tests."""

from __future__ import annotations

from nuplan_occ.pipeline.params import apply_overrides, default_params

FAST_OVERRIDES = {"reconstruct": {"method": "none", "object_method": "none"}, "load": {"context_seconds": 0.25}}
"""Raw points instead of surfaces and a shorter context, for tests that build many times (resume,
executors, concurrent writers): what they check (identical bytes, rows, failures) does not depend on the
surface method. The defaults (the torch solver, 1 s of context) are exercised by the damaged-blobs build
and the README build."""

FAST_CLI = [arg for stage, values in FAST_OVERRIDES.items() for key, value in values.items()
            for arg in ("--set", f"{stage}.{key}={value}")]
"""FAST_OVERRIDES as `nuplan-occ build` options."""


def build_params(fast: bool = True) -> dict:
    from nuplan_occ.stages import PIPELINE

    params = default_params(PIPELINE)
    return apply_overrides(params, FAST_OVERRIDES, "tests") if fast else params
