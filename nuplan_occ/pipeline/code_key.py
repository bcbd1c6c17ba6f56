"""The code a stage runs, as a hash: the source of its module and of every project module it imports,
transitively, so that no edit of that code can leave a stale cache entry behind.

Imports are read from the source (every `import` and `from ... import` statement, those inside functions
included), not from what happens to be loaded. A module counts when an import statement names it, or names
a package and one of its members is a submodule (`from nuplan_occ.points import knn`); a package named in an
import counts with its `__init__.py` and what that imports. Parent packages that Python initialises on the
way to a module are not followed (their `__init__` re-exports are counted where an import names them).
Only modules under the `nuplan_occ` package count: third-party code is pinned by the environment.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.util
from functools import lru_cache
from pathlib import Path

PROJECT_PACKAGE = "nuplan_occ"


@lru_cache(maxsize=None)
def module_file(name: str) -> Path | None:
    """The source file of project module `name` (a package's `__init__.py`), None when it is not a project
    module or does not exist."""
    if name != PROJECT_PACKAGE and not name.startswith(PROJECT_PACKAGE + "."):
        return None
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin)


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def imported_modules(name: str) -> set[str]:
    """The project modules that module `name`'s import statements name (see the module docstring)."""
    path = module_file(name)
    if path is None:
        return set()
    package = name if _is_package(path) else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                source = f"{base}.{node.module}" if node.module else base
            else:
                source = node.module or ""
            found.add(source)
            found.update(f"{source}.{alias.name}" for alias in node.names)
    return {module for module in found if module_file(module) is not None}


@lru_cache(maxsize=None)
def import_closure(name: str) -> tuple[str, ...]:
    """`name` and every project module it imports, transitively (sorted names)."""
    seen: set[str] = set()
    pending = [name]
    while pending:
        module = pending.pop()
        if module in seen or module_file(module) is None:
            continue
        seen.add(module)
        pending.extend(imported_modules(module) - seen)
    return tuple(sorted(seen))


@lru_cache(maxsize=None)
def code_version(module: str) -> str:
    """sha256 over the names and sources of `import_closure(module)`."""
    digest = hashlib.sha256()
    for name in import_closure(module):
        digest.update(name.encode() + b"\0")
        digest.update(module_file(name).read_bytes())  # type: ignore[union-attr]
    return digest.hexdigest()
