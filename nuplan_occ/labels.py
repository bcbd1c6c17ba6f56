"""Semantic label map (ids, names, colors) read from `nuplan_occ/schemas/labels.json`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ import schemas


@dataclass(frozen=True)
class LabelMap:
    """id -> name and RGB color; box category name -> id."""

    names: dict[int, str]
    colors: dict[int, tuple[int, int, int]]
    box_category_to_id: dict[str, int]

    def id_of(self, name: str) -> int:
        """Id of a class name; KeyError if unknown."""
        for class_id, class_name in self.names.items():
            if class_name == name:
                return class_id
        raise KeyError(name)

    def palette(self) -> np.ndarray:
        """(256, 3) uint8 lookup table id -> RGB (unused ids black)."""
        lut = np.zeros((256, 3), dtype=np.uint8)
        for class_id, rgb in self.colors.items():
            lut[class_id] = rgb
        return lut

    def to_dict(self) -> dict:
        """As stored in dataset metadata."""
        return schemas.load("labels")


def load_labels() -> LabelMap:
    """The project's label map."""
    data = schemas.load("labels")
    return LabelMap(
        names={c["id"]: c["name"] for c in data["classes"]},
        colors={c["id"]: tuple(c["color"]) for c in data["classes"]},
        box_category_to_id=dict(data["box_category_to_id"]),
    )


LABELS = load_labels()
BOX_CATEGORIES = tuple(LABELS.box_category_to_id)
"""The box categories of the logs (labels.json), in label-map order."""
EMPTY, OTHER = 0, 1
VEHICLE, BICYCLE, PEDESTRIAN, TRAFFIC_CONE, BARRIER, CZONE_SIGN, GENERIC_OBJECT = 2, 3, 4, 5, 6, 7, 8
ROAD, OTHER_GROUND, ROAD_LINE = 12, 13, 14
