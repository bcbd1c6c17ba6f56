import torch

from nuplan_occ.labels import BARRIER, OTHER_GROUND, PEDESTRIAN, ROAD, ROAD_LINE, VEHICLE
from occgen.layout import LAYOUT_CHANNELS, LAYOUT_CLASSES, downsample_layout, layout_from_semantics

NAMES = ["nothing"] + [name for name, _ in LAYOUT_CLASSES]


def test_layout_marks_ground_classes_and_object_footprints_per_column():
    sem = torch.zeros(4, 4, 6, dtype=torch.uint8)
    sem[0, :, 1] = ROAD
    sem[1, :, 1] = ROAD_LINE
    sem[2, :, 1] = OTHER_GROUND
    sem[0, 0, 2:5] = VEHICLE
    sem[2, 3, 4] = PEDESTRIAN
    sem[3, 3, 5] = BARRIER
    layout = layout_from_semantics(sem)
    assert layout.shape == (LAYOUT_CHANNELS, 4, 4)
    ch = {n: layout[i] for i, n in enumerate(NAMES)}
    assert ch["road"][0].tolist() == [1, 1, 1, 1] and ch["road_line"][1].sum() == 4
    assert ch["vehicle"][0, 0] == 1 and ch["vehicle"].sum() == 1
    assert ch["pedestrian"][2, 3] == 1 and ch["other_object"][3, 3] == 1
    assert ch["nothing"][3].tolist() == [1, 1, 1, 0]
    assert (layout.sum(0) >= 1).all()  # every real cell is non-zero: the zero layout means "no condition"


def test_downsampled_layout_holds_fractions():
    layout = torch.zeros(2, LAYOUT_CHANNELS, 8, 8)
    layout[:, 1, :2, :1] = 1
    small = downsample_layout(layout, 4)
    assert small.shape == (2, LAYOUT_CHANNELS, 2, 2)
    assert small[0, 1, 0, 0] == 2 / 16 and small[0, 1].sum() == 2 / 16
