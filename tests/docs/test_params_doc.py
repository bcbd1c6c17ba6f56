"""docs/params.md lists every declared build param with its current default, and nothing that is gone."""

from __future__ import annotations

import re
from pathlib import Path

from nuplan_occ.pipeline.params import default_params, param_rows
from nuplan_occ.stages import PIPELINE

PAGE = Path(__file__).resolve().parents[2] / "docs" / "params.md"


def _listed() -> dict[str, dict[str, str]]:
    """section -> param -> default cell, from the page's tables."""
    listed: dict[str, dict[str, str]] = {}
    section = ""
    for line in PAGE.read_text().splitlines():
        if line.startswith("## "):
            section = line[3:].strip()
        row = re.match(r"\| `(\w+)` \| [^|]* \| ([^|]*) \|", line)
        if row:
            listed.setdefault(section, {})[row.group(1)] = row.group(2).strip()
    return listed


def test_every_param_is_on_the_page_with_its_default():
    listed = _listed()
    declared = default_params(PIPELINE)
    assert set(listed) == set(declared)
    for section, value in declared.items():
        rows = param_rows(type(value))
        assert set(listed[section]) == {row["name"] for row in rows}, section
        for row in rows:
            default = row["default"]
            text = ", ".join(str(v) for v in default) or "(none)" if isinstance(default, tuple) else str(default)
            assert listed[section][row["name"]] == text, f"{section}.{row['name']}"
