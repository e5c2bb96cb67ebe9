"""Plausibility metrics on hand-built cases with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import DOF_NAMES
from crisp_gym.metrics import (
    box_signed_distance,
    contact_height_error,
    foot_skating,
    motion_plausibility,
    scene_model,
    scene_penetration,
    sole_points,
    support_tops,
)
from crisp_gym.motion import Motion
from crisp_gym.scene import Box, floor_box


def test_box_signed_distance_inside_outside_and_rotated():
    box = Box(center=[0, 0, 0.5], half_size=[1.0, 1.0, 0.5])
    d = box_signed_distance(np.array([[0, 0, 0.97], [0, 0, 1.2], [1.3, 0, 1.4], [0, 0, 0.5]]), [box])
    np.testing.assert_allclose(d, [-0.03, 0.2, np.hypot(0.3, 0.4), -0.5])
    rotated = Box(center=[0, 0, 0], rotation=Rotation.from_euler("z", 45, degrees=True).as_matrix(),
                  half_size=[1.0, 0.1, 0.1])
    np.testing.assert_allclose(box_signed_distance(np.array([[0.5, 0.5, 0.0], [0.0, 0.0, 0.3]]), [rotated]),
                               [-0.1, 0.2], atol=1e-12)
    # A union takes the nearer box.
    assert box_signed_distance(np.array([[0, 0, 1.2]]), [box, Box(center=[0, 0, 1.25], half_size=[1, 1, 0.1])])[0] \
        == pytest.approx(-0.05)


def test_support_tops_for_level_and_tilted_boxes():
    step = Box(center=[1.0, 0.0, 0.1], half_size=[0.2, 0.5, 0.1])
    tilted = Box(center=[0, 3, 0], rotation=Rotation.from_euler("x", 30, degrees=True).as_matrix(),
                 half_size=[0.5, 1.0, 0.1])
    tops = support_tops(np.array([[1.0, 0.0], [5.0, 0.0], [0.0, 3.0]]), [floor_box(), step, tilted])
    np.testing.assert_allclose(tops[0, :2], [0.0, 0.2])
    assert np.isnan(tops[1, 1]) and np.isnan(tops[0, 2])
    assert tops[2, 2] == pytest.approx(0.1 / np.cos(np.pi / 6))  # the slanted top above its centre


def test_foot_skating_known_speed_and_contact_pairs():
    fps = 30.0
    t = np.arange(31) / fps
    pos = np.zeros((31, 2, 3))
    pos[:, 0, 0] = 0.02 * t  # sliding at 2 cm/s
    pos[:, 1, 1] = 0.5 * t  # 0.5 m/s, but in contact for one frame at a time only
    contacts = np.zeros((31, 2), dtype=bool)
    contacts[:, 0] = True
    contacts[::2, 1] = True
    stats = foot_skating(pos, contacts, fps)
    assert stats.mean_speed == pytest.approx(0.02) and stats.samples == 30 and stats.fraction_over == 0.0
    pos[:, 0, 0] = 0.2 * t
    assert foot_skating(pos, contacts, fps).fraction_over == 1.0
    assert foot_skating(pos, np.zeros_like(contacts), fps).samples == 0
    with pytest.raises(ValueError, match="positions must be"):
        foot_skating(pos[..., :2], contacts, fps)


def test_contact_height_error_measures_the_gap_to_the_nearest_top():
    boxes = [floor_box(), Box(center=[1.0, 0.0, 0.1], half_size=[0.2, 0.5, 0.1])]
    soles = np.array([[[0.0, 0.0, 0.004], [1.0, 0.0, 0.19]], [[0.0, 0.0, 0.3], [1.0, 0.0, 0.5]]])
    contacts = np.array([[True, True], [False, False]])
    np.testing.assert_allclose(contact_height_error(soles, contacts, boxes), [0.004, 0.01])
    far = np.array([[[100.0, 0.0, 0.0]]])
    assert contact_height_error(far, np.ones((1, 1), dtype=bool), boxes)[0] == np.inf


def _standing(root_z: float) -> Motion:
    dof = np.zeros((2, len(DOF_NAMES)))
    return Motion(fps=30.0, root_pos=np.tile([0.0, 0.0, root_z], (2, 1)), root_quat=np.tile([1.0, 0, 0, 0], (2, 1)),
                  dof_pos=dof)


def test_scene_penetration_and_soles_of_the_posed_humanoid():
    model = scene_model([floor_box()])
    rest = sole_points(model, _standing(1.0).qpos())
    lift = 1.0 - rest[0, :, 2].min()  # the pelvis height that puts the soles on the floor
    soles = sole_points(model, _standing(lift).qpos())
    np.testing.assert_allclose(soles[..., 2], 0.0, atol=1e-9)
    assert scene_penetration(model, _standing(lift + 0.01).qpos()).max() == 0.0
    np.testing.assert_allclose(scene_penetration(model, _standing(lift - 0.03).qpos()), 0.03, atol=1e-6)


def test_motion_plausibility_of_a_grounded_standing_pose():
    model = scene_model([floor_box()])
    lift = 1.0 - sole_points(model, _standing(1.0).qpos())[0, :, 2].min()
    motion = _standing(lift)
    with pytest.raises(ValueError, match="contacts"):
        motion_plausibility([floor_box()], motion)
    contacts = np.zeros((2, 24), dtype=bool)
    contacts[:, [3, 4, 7, 8]] = True
    p = motion_plausibility([floor_box()], Motion(fps=30.0, root_pos=motion.root_pos, root_quat=motion.root_quat,
                                                  dof_pos=motion.dof_pos, contacts=contacts), model)
    assert p.penetration_max < 1e-6 and p.contact_height_max < 1e-9 and p.skating.mean_speed == 0.0
    assert p.contact_samples == 8
