"""What a pipeline stage declares: its name, named inputs and outputs, typed params and the pure
function that runs it. Stage modules in `stages/` build one `Stage` each (wiring only)."""

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
    """

    name: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    params_type: type
    run: Callable[[dict[str, Any], Any], dict[str, Any]]
    code: tuple[str, ...] = ()
    cache: bool = True
    doc: str = field(default="", compare=False)

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
