"""The build DAG, top to bottom: one module per stage, each declaring its inputs, outputs, typed params and
the library functions it calls. `PIPELINE` is the one place that holds their order.

    scene stages: load -> split -> filter -> register -> label_map -> track -> lidar_rays -> aggregate
                  -> reconstruct -> support
    frame stages, streamed frame by frame: voxelize -> label -> visibility -> write
"""

from nuplan_occ.stages import (aggregate, filter, label, label_map, lidar_rays, load, reconstruct, register, split,
                               support, track, visibility, voxelize, write)

PIPELINE = [
    load.STAGE,
    split.STAGE,
    filter.STAGE,
    register.STAGE,
    label_map.STAGE,
    track.STAGE,
    lidar_rays.STAGE,
    aggregate.STAGE,
    reconstruct.STAGE,
    support.STAGE,
    voxelize.STAGE,
    label.STAGE,
    visibility.STAGE,
    write.STAGE,
]
"""The stages in execution order; every stage's inputs are produced by the stages before it."""
