"""The build DAG, top to bottom. Each module declares one Stage: inputs, outputs, typed params, and the
pure functions of `nuplan_occ` it calls.

    scene stages: load -> split -> filter -> register -> track -> lidar_rays -> aggregate -> reconstruct -> support
                  -> label_map
    frame stages, streamed frame by frame: voxelize -> label -> visibility -> write
"""

from nuplan_occ.stages import aggregate, filter, label, load, reconstruct, register, split, support, track, visibility, voxelize, write

PIPELINE = [
    load.STAGE,
    split.STAGE,
    filter.STAGE,
    register.STAGE,
    track.STAGE,
    visibility.RAYS_STAGE,
    aggregate.STAGE,
    reconstruct.STAGE,
    support.STAGE,
    label.MAP_STAGE,
    voxelize.STAGE,
    label.STAGE,
    visibility.STAGE,
    write.STAGE,
]
"""The stages in execution order; every stage's inputs are produced by the stages before it."""
