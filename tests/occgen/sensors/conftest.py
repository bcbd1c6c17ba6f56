import numpy as np
import pytest

from nuplan_occ.grid import GridSpec

SMALL_GRID = GridSpec(-16.0, 16.0, -16.0, 16.0, -3.0, 5.0, 0.25)


@pytest.fixture
def small_grid() -> GridSpec:
    return SMALL_GRID


@pytest.fixture
def street() -> np.ndarray:
    """A small street on SMALL_GRID: road at z in [-0.5, -0.25), a barrier wall at x = 9 m, a car box."""
    sem = np.zeros(SMALL_GRID.shape, np.uint8)
    sem[:, :, 10] = 12
    sem[100, :, 8:24] = 6
    sem[70:86, 40:50, 11:17] = 2
    return sem


@pytest.fixture
def street_dataset(tmp_path, street) -> str:
    """A dataset root on SMALL_GRID holding two frames of `street` (tokens 000..0, 000..1)."""
    from nuplan_occ.storage import DatasetWriter, FrameRecord

    root = str(tmp_path / "ds")
    w = DatasetWriter(root, metadata={"params": {}}, grid=SMALL_GRID)
    frames = [FrameRecord(log="log", log_id=0, scene_token="ab" * 8, scene_name="scene-0000", frame_index=i,
                          token=f"{i:016x}", timestamp_us=i, ego_to_global=np.eye(4), arrays={"semantics": street},
                          columns={}, status="ok") for i in range(2)]
    w.commit(w.write_shard("log/scene-0000", frames))
    return root
