"""nuplan_occ.geometry: rotation angles against rotations built from a known axis and angle."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nuplan_occ.geometry import rotation_angle_deg


def test_rotation_angle_of_one_rotation_and_of_a_stack():
    angles = np.array([0.0, 0.5, 30.0, 90.0, 179.0])
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    stack = Rotation.from_rotvec(np.radians(angles)[:, None] * axis).as_matrix()
    assert isinstance(rotation_angle_deg(stack[2]), float)
    assert rotation_angle_deg(stack[2]) == pytest.approx(30.0, abs=1e-9)
    assert rotation_angle_deg(stack).shape == (5,)
    assert np.allclose(rotation_angle_deg(stack), angles, atol=1e-6)
    assert np.allclose(rotation_angle_deg(stack.reshape(5, 1, 3, 3)), angles[:, None], atol=1e-6)


def test_rotation_angle_clips_rounding_past_the_identity():
    almost = np.eye(3) * (1.0 + 1e-12)  # trace just above 3: arccos would be NaN without the clip
    assert rotation_angle_deg(almost) == 0.0
