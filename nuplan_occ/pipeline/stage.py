"""What a pipeline stage declares: its name, named inputs and outputs, typed params and the pure
function that runs it. Stage modules in `stages/` build one `Stage` each (wiring only).

Two granularities: a scene stage runs once per scene and its outputs are scene artifacts (cached); a
frame stage (per_frame=True) runs once per output frame, in DAG order, and its outputs are that frame's
artifacts, released once the frame is written (see nuplan_occ.pipeline.runner)."""

from __future__ import annotations

import hashlib
import importlib
import inspect
from pathlib import Path
from dataclasses import dataclass, field
from typing import Any, Callable


@dataclass(frozen=True)
class Stage:
    """One step of the DAG.

    run(inputs, params) -> outputs: `inputs` holds the artifacts named in `inputs` (produced by earlier
    stages, or the scene's source data for the first stage); it returns a dict with exactly `outputs`.
    code: modules whose source is part of this stage's cache key (a change in them reruns the stage).
    cache: False for stages whose outputs are cheaper to recompute than to store (e.g. reading input).
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
    the frames share, e.g. a spatial index; made from the inputs by the stage's own code, so the stage's
    cache key covers it).
    """

    name: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    params_type: type
    run: Callable[[dict[str, Any], Any], dict[str, Any]]
    code: tuple[str, ...] = ()
    cache: bool = True
    item_outputs: tuple[str, ...] = ()
    doc: str = field(default="", compare=False)
    per_frame: bool = False
    params_section: str = ""
    prepare: Callable[[dict[str, Any], Any], dict[str, Any]] | None = None

    @property
    def params_name(self) -> str:
        """The section of the build params this stage reads."""
        return self.params_section or self.name

    def code_version(self) -> str:
        """sha256 over the source of the stage's own module and its declared code modules (a package
        counts with every .py file below it)."""
        digest = hashlib.sha256()
        modules = [inspect.getmodule(self.run).__name__, *self.code]  # type: ignore[union-attr]
        for name in modules:
            module = importlib.import_module(name)
            files = sorted(Path(module.__path__[0]).rglob("*.py")) if hasattr(module, "__path__") else [Path(module.__file__)]
            for path in files:
                digest.update(path.name.encode())
                digest.update(path.read_bytes())
        return digest.hexdigest()
