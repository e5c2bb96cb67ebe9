"""Centre of pressure by inverse dynamics: statics, a known acceleration, and the synthetic clips."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from crisp_gym.balance import GRAVITY, distance_outside_hull, motion_balance
from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, FEET, HumanoidConfig, build_humanoid
from crisp_gym.motion import Motion
from crisp_gym.synth.clips import KINDS, make_clip


def _standing(frames: int, root_x: np.ndarray | None = None) -> Motion:
    """The rest pose (arms out, feet on z = 0), its root moved along x by ``root_x``."""
    model = build_humanoid(HumanoidConfig())
    root = np.tile(model.qpos0[:3], (frames, 1))
    if root_x is not None:
        root[:, 0] += root_x
    contacts = np.zeros((frames, len(BODY_NAMES)), dtype=bool)
    contacts[:, [BODY_NAMES.index(b) for b in FEET]] = True
    return Motion(fps=30.0, root_pos=root, root_quat=np.tile(model.qpos0[3:7], (frames, 1)),
                  dof_pos=np.zeros((frames, len(DOF_NAMES))), contacts=contacts)


def _centre_of_mass(motion: Motion, frame: int) -> np.ndarray:
    model = build_humanoid(HumanoidConfig())
    data = mujoco.MjData(model)
    data.qpos[:] = motion.qpos()[frame]
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    return data.subtree_com[model.body("Pelvis").id].copy()


def test_standing_still_presses_below_the_centre_of_mass():
    motion = _standing(5)
    balance = motion_balance(motion)
    com = _centre_of_mass(motion, 2)
    np.testing.assert_allclose(balance.cop[2], com[:2], atol=1e-6)
    assert balance.vertical_force[2] == pytest.approx(1.0, abs=1e-6)
    assert balance.outside[2] < 0  # above the feet


def test_a_rigid_acceleration_moves_the_centre_of_pressure_by_height_times_acceleration_over_g():
    # Root translated as x(t) = a t^2 / 2: the ground pushes m (a, 0, g) through a point that
    # lies z_com * a / g behind the centre of mass (the moment of m a about it balances m g).
    a, frames = 2.0, 9
    t = np.arange(frames) / 30.0
    motion = _standing(frames, root_x=0.5 * a * t**2)
    balance = motion_balance(motion)
    k = frames // 2
    com = _centre_of_mass(motion, k)
    assert balance.cop[k, 0] == pytest.approx(com[0] - com[2] * a / GRAVITY, abs=1e-4)
    assert balance.cop[k, 1] == pytest.approx(com[1], abs=1e-4)
    assert balance.outside[k] > 0.1  # 19 cm behind the centre of mass: behind the heels


def test_frames_supported_by_another_body_or_by_nothing_are_not_judged():
    motion = _standing(5)
    contacts = motion.contacts.copy()
    contacts[1, BODY_NAMES.index("Pelvis")] = True  # seated
    contacts[3] = False  # airborne
    balance = motion_balance(Motion(fps=motion.fps, root_pos=motion.root_pos, root_quat=motion.root_quat,
                                    dof_pos=motion.dof_pos, contacts=contacts))
    assert np.isnan(balance.outside[[1, 3]]).all() and np.isfinite(balance.outside[[0, 2, 4]]).all()
    assert np.isnan(balance.cop[3]).all() and np.isfinite(balance.cop[1]).all()


def test_without_contact_labels_both_feet_count_as_planted():
    motion = _standing(5)
    unlabelled = motion_balance(Motion(fps=motion.fps, root_pos=motion.root_pos, root_quat=motion.root_quat,
                                       dof_pos=motion.dof_pos))
    np.testing.assert_allclose(unlabelled.outside, motion_balance(motion).outside)


def test_distance_outside_hull():
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert distance_outside_hull(square, np.array([0.5, 0.5])) == pytest.approx(-0.5)
    assert distance_outside_hull(square, np.array([1.25, 0.5])) == pytest.approx(0.25)
    assert distance_outside_hull(square[:2], np.array([0.5, 0.0])) == np.inf


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_synthetic_clips_ask_for_a_centre_of_pressure_the_feet_can_give(kind, seed):
    """The generator plans the pelvis as an inverted pendulum over the footsteps and keeps its
    height smooth: the keyframed first generator put it more than 10 cm outside the feet on
    11-40 % of the frames of the bundled clips (up to 1.5 m, stopping a walk)."""
    _, motion, _ = make_clip(kind, seed)
    balance = motion_balance(motion)
    assert np.isfinite(balance.outside).mean() > 0.5
    assert balance.share_outside(0.10) < 0.06
    assert np.nanmax(balance.outside) < 0.25
