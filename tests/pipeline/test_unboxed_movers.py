"""A moving vehicle the log has no box for (the synthetic world leaves the mover nearest the ego route
unannotated, as a missed detection) is occupied in each frame where it is, labeled vehicle, and nowhere
else: its frame's own points that the aggregate removed as dynamic are voxelized in that frame, with the points
of the frames around gathered onto it by its motion and filled as the solid they outline."""

from __future__ import annotations

import numpy as np

from nuplan_occ import open_dataset
from nuplan_occ.labels import VEHICLE


def _unboxed_truth_instance(built, truth) -> int:
    """The truth instance with the most observed voxels that no built instance covers in any frame."""
    observed, covered = {}, set()
    for i in range(len(built)):
        frame = built.get(i, keys=("instance",))
        reference = truth[truth.index_of_token(frame["token"])]
        seen = reference["mask_lidar"] & (reference["instance"] > 0)
        for instance in np.unique(reference["instance"][seen]):
            voxels = seen & (reference["instance"] == instance)
            observed[int(instance)] = observed.get(int(instance), 0) + int(voxels.sum())
            if (frame["instance"][voxels] > 0).any():
                covered.add(int(instance))
    unboxed = {k: v for k, v in observed.items() if k not in covered}
    assert unboxed, "the synthetic world should hold a mover without a box"
    return max(unboxed, key=unboxed.get)


def test_unboxed_mover_is_occupied_where_it_is_and_nowhere_else(reference_build, synthetic_root):
    built, truth = open_dataset(str(reference_build)), open_dataset(str(synthetic_root / "truth"))
    mover = _unboxed_truth_instance(built, truth)
    qa = built.column("qa_unboxed_mover_voxels").to_pylist()
    painted_total = on_vehicle = frames_with_mover = observed = covered = 0
    for i in range(len(built)):
        frame = built.get(i, keys=("semantics", "instance"))
        reference = truth[truth.index_of_token(frame["token"])]
        painted = (frame["semantics"] == VEHICLE) & (frame["instance"] == 0)
        painted_total += int(painted.sum())
        on_vehicle += int((painted & (reference["semantics"] == VEHICLE)).sum())
        seen = (reference["instance"] == mover) & reference["mask_lidar"]
        observed += int(seen.sum())
        covered += int((seen & (frame["semantics"] == VEHICLE)).sum())
        if seen.sum() >= 150:
            frames_with_mover += 1
            assert qa[i] > 0, f"frame {i}: the mover's points gave no voxel"
    assert frames_with_mover >= 5
    assert painted_total >= 20 * frames_with_mover
    assert on_vehicle / painted_total >= 0.9  # painted where a vehicle is now: no trail
    assert covered / observed >= 0.2  # its own points alone cover about a seventh of its observed voxels
