"""BEV layout condition derived from the semantics grid itself.

The dataset stores no separate map/box layout, so the layout is read off the occupancy: per BEV cell
(x, y), channel c is 1 if any voxel of the column has one of the classes of `LAYOUT_CLASSES[c]`:
map classes (road, road_line, other_ground — the ground layer) and object classes projected to BEV
(vehicle, bicycle, pedestrian, other objects), which are the footprints of the boxes. Channel 0
("nothing") marks columns with none of them, so every real layout cell has at least one channel set
and the all-zero layout is free to mean "no condition" (classifier-free guidance).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from nuplan_occ import labels as L

LAYOUT_CLASSES: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("road", (L.ROAD,)),
    ("road_line", (L.ROAD_LINE,)),
    ("other_ground", (L.OTHER_GROUND,)),
    ("vehicle", (L.VEHICLE,)),
    ("bicycle", (L.BICYCLE,)),
    ("pedestrian", (L.PEDESTRIAN,)),
    ("other_object", (L.OTHER, L.TRAFFIC_CONE, L.BARRIER, L.CZONE_SIGN, L.GENERIC_OBJECT)),
)
LAYOUT_CHANNELS = len(LAYOUT_CLASSES) + 1


def layout_from_semantics(sem: torch.Tensor) -> torch.Tensor:
    """Class ids [..., X, Y, Z] -> layout float [..., LAYOUT_CHANNELS, X, Y] (0/1; channel 0 = nothing)."""
    present = []
    for _, ids in LAYOUT_CLASSES:
        hit = torch.zeros(sem.shape[:-1], dtype=torch.bool, device=sem.device)
        for class_id in ids:
            hit |= (sem == class_id).any(dim=-1)
        present.append(hit)
    stacked = torch.stack(present, dim=-3)
    nothing = ~stacked.any(dim=-3, keepdim=True)
    return torch.cat([nothing, stacked], dim=-3).float()


def downsample_layout(layout: torch.Tensor, factor: int) -> torch.Tensor:
    """Average-pool [..., Cb, X, Y] by `factor` in X and Y: per latent cell, the fraction of each channel."""
    lead = layout.shape[:-3]
    flat = layout.reshape(-1, *layout.shape[-3:])
    pooled = F.avg_pool2d(flat, factor)
    return pooled.reshape(*lead, *pooled.shape[-3:])
