"""What a pipeline stage declares: its name, named inputs and outputs, typed params and the pure
function that runs it. The modules of `nuplan_occ/stages/` build one `Stage` each (wiring only).

Two granularities: a scene stage runs once per scene and its outputs are scene artifacts (cached); a
frame stage (per_frame=True) runs once per output frame, in DAG order, and its outputs are that frame's
artifacts, released once the frame is written (see nuplan_occ.pipeline.runner)."""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from nuplan_occ.pipeline.code_key import code_version


@dataclass(frozen=True)
class Stage:
    """One step of the DAG.

    run(inputs, params) -> outputs: `inputs` holds the artifacts named in `inputs` (produced by earlier
    stages, or the scene's source data for the first stage); it returns a dict with exactly `outputs`.
    params_type: the params dataclass the stage declares (None for a stage that reads another stage's
    section, named by params_section).
    cache: False for stages whose outputs are cheaper to recompute than to store (e.g. reading input).
    kept: the default work-folder policy keeps this stage's cache entries after the scene is published
    (small entries that make a param change cheap; see nuplan_occ.pipeline.publish).
    item_outputs: outputs that are sequences of one element per sweep or per frame (the stage's doc says which):
    the cache stores them one element at a time and the stages after this one read them back one element per access
    (pipeline.cache.StoredItems), so a scene's per-sweep outputs are not held in memory; their readers
    may only index or iterate them. run may return an item output as a one-pass iterable (a generator, or a
    sequence computing each element on access): its elements are then made while the cache stores them, one
    at a time, and the stage's time includes storing them; other outputs it fills during that pass are
    complete once the pass ends (the cache stores the entry after the items).
    per_frame: a frame stage: run(inputs, frame, params) -> frame outputs, where `inputs` holds the scene
    artifacts named in `inputs` and `frame` the frame's artifacts so far ("position": the sweep's position in
    the scene, plus the outputs of earlier frame stages); it may set "failure" (reason) to skip the frame's
    remaining stages but the last, which turns the frame into its record.
    params_section: the params section it reads (default: its name), when two stages share one.
    prepare: frame stages only, optional: prepare(inputs, params) -> dict, run once per scene before its
    first frame on the stage's scene inputs; its outputs are added to them for every frame (per-scene work
    the frames share, e.g. a spatial index).
    sources: stages reading the scene task only, optional: sources(task, params) -> the input files the stage
    reads for the scene besides the log's DB (point cloud blobs, the map); their fingerprints join the task's
    cache key, so a file put back or replaced rebuilds exactly the scenes that read it.
    """

    name: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    params_type: type | None
    run: Callable[..., dict[str, Any]]
    cache: bool = True
    kept: bool = False
    item_outputs: tuple[str, ...] = ()
    per_frame: bool = False
    params_section: str = ""
    prepare: Callable[[dict[str, Any], Any], dict[str, Any]] | None = None
    sources: Callable[[Any, Any], list[Path]] | None = None

    @property
    def params_name(self) -> str:
        """The section of the build params this stage reads."""
        return self.params_section or self.name

    def code_version(self) -> str:
        """Hash of the stage module's source and of every project module it imports, transitively
        (nuplan_occ.pipeline.code_key): any edit of the code the stage runs changes it."""
        return code_version(inspect.getmodule(self.run).__name__)  # type: ignore[union-attr]
