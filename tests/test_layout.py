"""The arrows of the architecture (CONTRIBUTING.md, Layout): the library never imports the stages, the CLI,
occgen or the benchmarks; the stages never import each other; occgen uses only the public API."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PUBLIC_API = ("nuplan_occ", "nuplan_occ.dataset", "nuplan_occ.torch", "nuplan_occ.grid", "nuplan_occ.labels",
              "nuplan_occ.storage", "nuplan_occ.io.reader", "nuplan_occ.io.pcd", "nuplan_occ.io.types",
              "nuplan_occ.cli.errors")
"""What occgen may import: the dataset API (open, read, torch), the grid and labels, the dataset writer, the
nuPlan reader and point-cloud codec, and the CLI's one-line error handling."""


def imports_of(path: Path) -> set[str]:
    """Every module an import statement of `path` names (absolute imports; the project uses no relative ones)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}: relative import"
            names.add(node.module or "")
    return names


def modules(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def _under(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def test_the_library_imports_nothing_built_on_it():
    library = [p for p in modules("nuplan_occ") if p.relative_to(ROOT / "nuplan_occ").parts[0] not in ("stages", "cli")]
    assert len(library) > 100
    upward = {str(path.relative_to(ROOT)): names for path in library
              if (names := [name for name in imports_of(path) if any(_under(name, top) for top in
                            ("nuplan_occ.stages", "nuplan_occ.cli", "occgen", "benchmarks"))])}
    assert not upward


def test_stages_import_the_library_and_not_each_other():
    for path in modules("nuplan_occ/stages"):
        if path.name == "__init__.py":
            continue
        others = [name for name in imports_of(path) if _under(name, "nuplan_occ.stages") or _under(name, "nuplan_occ.cli")]
        assert not others, f"{path.relative_to(ROOT)} imports {others}"


def test_occgen_uses_only_the_public_api():
    for path in modules("occgen"):
        private = [name for name in imports_of(path) if _under(name, "nuplan_occ") and name not in PUBLIC_API]
        assert not private, f"{path.relative_to(ROOT)} imports {private}"
