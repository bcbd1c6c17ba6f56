"""Label maps from a release's ids to ours: the named maps of `nuplan_occ/schemas/release_labels.json`, our
own ids ("nuplan-occ", for files our `export --format uniscene` wrote) or a FILE.json following
`nuplan_occ/schemas/release_label_map.json`."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import jsonschema
import numpy as np

from nuplan_occ import schemas
from nuplan_occ.labels import LABELS
from nuplan_occ.release.errors import ReleaseImportError

OURS = "nuplan-occ"
DEFAULT_BY_LAYOUT = {"sparse4": "raw-sparse", "sparse2": "raw-sparse", "dense": "uniscene"}


@dataclass(frozen=True)
class ReleaseLabelMap:
    """name, and `classes`: source id -> (source name, our id)."""

    name: str
    classes: dict[int, tuple[str, int]]

    def to_dict(self) -> dict:
        """As recorded in dataset.json (nuplan_occ/schemas/release_label_map.json layout)."""
        return {"name": self.name, "classes": [{"id": i, "name": n, "ours": o}
                                               for i, (n, o) in sorted(self.classes.items())]}

    def to_ours(self, ids: np.ndarray, where: str) -> np.ndarray:
        """Our uint8 ids of an integer array of source ids (any shape).

        Raises ReleaseImportError naming `where` (the file) for ids the map does not list."""
        found = np.unique(ids)
        bad = [int(i) for i in found if int(i) not in self.classes]
        if bad:
            known = ", ".join(str(i) for i in sorted(self.classes))
            raise ReleaseImportError(f"{where}: label ids {bad} are not in label map {self.name!r} (ids {known}); "
                                     f"choose another --labels (uniscene, raw-sparse, {OURS} or FILE.json)")
        lut = np.zeros(int(found.max()) + 1 if found.size else 1, dtype=np.uint8)
        for source_id, (_, ours) in self.classes.items():
            if source_id < lut.size:
                lut[source_id] = ours
        return lut[ids]


def _from_dict(data: dict, where: str) -> ReleaseLabelMap:
    try:
        jsonschema.validate(data, schemas.load("release_label_map"))
    except jsonschema.ValidationError as exc:
        raise ReleaseImportError(f"{where}: not a label map ({exc.message})") from None
    classes: dict[int, tuple[str, int]] = {}
    for entry in data["classes"]:
        if entry["id"] in classes:
            raise ReleaseImportError(f"{where}: label id {entry['id']} is listed twice")
        if entry["ours"] not in LABELS.names:
            raise ReleaseImportError(f"{where}: id {entry['id']} maps to {entry['ours']}, not one of our ids "
                                     f"{sorted(LABELS.names)}")
        classes[int(entry["id"])] = (entry["name"], int(entry["ours"]))
    return ReleaseLabelMap(data["name"], classes)


def named_maps() -> tuple[str, ...]:
    """Names accepted by `load_label_map` besides a file path."""
    return (*schemas.load("release_labels")["maps"], OURS)


def load_label_map(spec: str) -> ReleaseLabelMap:
    """A named map (`named_maps()`) or a FILE.json path; ReleaseImportError names the bad file."""
    if spec == OURS:
        return ReleaseLabelMap(OURS, {i: (name, i) for i, name in LABELS.names.items()})
    maps = schemas.load("release_labels")["maps"]
    if spec in maps:
        return _from_dict(maps[spec], f"schemas/release_labels.json ({spec})")
    path = Path(spec)
    if not path.is_file():
        raise ReleaseImportError(f"{spec}: neither a label map name ({', '.join(named_maps())}) nor a file")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ReleaseImportError(f"{path}: cannot read label map ({exc})") from None
    return _from_dict(data, str(path))
