"""Centre of pressure by inverse dynamics: statics, a known acceleration, and the synthetic clips;
followability (where a motion asks more than feet can give) and standing a motion on its
supporting feet, on motions with a known answer."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from crisp_gym.balance import (
    GRAVITY,
    _spans,
    distance_outside_hull,
    followability,
    motion_balance,
    plant_supporting_feet,
)
from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, FEET, HumanoidConfig, build_humanoid
from crisp_gym.motion import Motion, side_sole_heights
from crisp_gym.synth.clips import KINDS, make_clip
from tests.conftest import fold_leg


def _standing(frames: int, root_x: np.ndarray | None = None, root_z: np.ndarray | None = None) -> Motion:
    """The rest pose (arms out, feet on z = 0), its root moved along x by ``root_x`` and up by ``root_z``."""
    model = build_humanoid(HumanoidConfig())
    root = np.tile(model.qpos0[:3], (frames, 1))
    if root_x is not None:
        root[:, 0] += root_x
    if root_z is not None:
        root[:, 2] += root_z
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


def _unlabelled(motion: Motion) -> Motion:
    return Motion(fps=motion.fps, root_pos=motion.root_pos, root_quat=motion.root_quat, dof_pos=motion.dof_pos)


def test_standing_on_the_floor_is_followable():
    follow = followability(_unlabelled(_standing(30)))
    assert follow.outside == 0.0 and follow.unsupported == 0.0 and follow.spans == ()
    assert "a body can follow it" in follow.describe()


def test_feet_that_hover_while_the_body_needs_carrying_are_flagged():
    """Standing still 5 cm above the floor: the ground must carry the whole weight, and no foot
    reaches it (a sliding foot would, and is not flagged)."""
    follow = followability(_unlabelled(_standing(30, root_z=np.full(30, 0.05))))
    assert follow.unsupported == 1.0 and follow.spans == ((0, 30),)
    assert "frames 0-29" in follow.describe()
    sliding = followability(_unlabelled(_standing(30, root_x=np.linspace(0.0, 1.0, 30))))
    assert sliding.unsupported == 0.0


def test_a_body_in_free_fall_asks_nothing_of_the_ground():
    t = np.arange(20) / 30.0
    follow = followability(_unlabelled(_standing(20, root_z=0.5 - 0.5 * GRAVITY * t**2 + 0.5 * GRAVITY * t[-1] ** 2)))
    # The feet are off the floor, but nothing pushes on them; only the end frames, whose
    # accelerations are not measured (their velocities repeat their neighbours'), look held.
    assert follow.unsupported <= 2 / 20 and follow.spans == ()


def test_an_acceleration_the_feet_cannot_give_is_flagged_where_it_happens():
    # 2 m/s^2 puts the centre of pressure 19 cm behind the centre of mass, behind the heels
    # (test above); standing still before and after it is followable.
    x = np.zeros(60)
    t = np.arange(20) / 30.0
    x[20:40] = 0.5 * 2.0 * t**2
    x[40:] = x[39] + 2.0 * t[-1] * np.arange(1, 21) / 30.0  # then gliding at constant speed
    follow = followability(_unlabelled(_standing(60, root_x=x)))
    assert len(follow.spans) == 1
    first, end = follow.spans[0]
    assert 18 <= first <= 21 and 38 <= end <= 42  # the accelerating frames (give or take the differences)
    assert follow.outside == pytest.approx((end - first) / 60, abs=0.02)


def test_flagged_runs_join_across_short_gaps_and_short_runs_are_dropped():
    flags = np.zeros(30, dtype=bool)
    flags[[2, 3, 4, 6, 7, 20, 25, 26, 27]] = True
    assert _spans(flags, bridge=2, min_span=3) == ((2, 8), (25, 28))
    assert _spans(flags, bridge=1, min_span=3) == ((2, 5), (25, 28))
    assert _spans(flags, bridge=6, min_span=1) == ((2, 8), (20, 28))


def _crouched(frames: int, root_y: np.ndarray | None = None, lift: float = 0.3, spread: float = 0.0) -> Motion:
    """Unlabelled: both legs folded by ``lift`` rad at hip and knee and back at the ankle (the feet
    level, 3.7 cm up at 0.3 rad) and spread apart by ``spread`` rad each at the hip (the feet kept
    level by the ankle), the pelvis at its rest height and moved sideways by ``root_y``."""
    motion = _unlabelled(_standing(frames))
    dof = motion.dof_pos.copy()
    for side, sign in (("L", 1.0), ("R", -1.0)):
        fold_leg(dof, side, lift)
        dof[:, DOF_NAMES.index(f"{side}_Hip_x")] = sign * spread
        dof[:, DOF_NAMES.index(f"{side}_Ankle_x")] = -sign * spread
    root = motion.root_pos.copy()
    if root_y is not None:
        root[:, 1] += root_y
    return Motion(fps=motion.fps, root_pos=root, root_quat=motion.root_quat, dof_pos=dof)


def test_a_body_held_up_on_hovering_feet_is_stood_on_them():
    """Standing still, feet wide apart and 3-5 cm up: the ground must carry the whole weight with
    its centre of pressure between the feet, more than 10 cm from either sole, so both come down
    onto the floor by unbending the legs; the pelvis stays, and nothing is left unsupported."""
    model = build_humanoid(HumanoidConfig())
    wide = _crouched(30, spread=0.25)
    # lowered by what spreading straight legs raises the feet: the folded legs can then reach the floor
    rise = side_sole_heights(_crouched(2, lift=0.0, spread=0.25), model)[0, 0]
    motion = Motion(fps=wide.fps, root_pos=wide.root_pos - [0.0, 0.0, rise], root_quat=wide.root_quat,
                    dof_pos=wide.dof_pos)
    sole = side_sole_heights(motion, model)
    assert np.all((sole > 0.03) & (sole < 0.05)) and followability(motion).unsupported == 1.0
    planted = plant_supporting_feet(motion, model)
    after = side_sole_heights(planted, model)
    assert np.all((after >= -1e-4) & (after <= 3e-3))  # as plant_feet, 2 mm count as on the floor
    np.testing.assert_array_equal(planted.root_pos, motion.root_pos)
    assert followability(planted).unsupported == 0.0
    # out of reach (the same stance 20 cm higher) nothing is done
    high = Motion(fps=motion.fps, root_pos=motion.root_pos + [0.0, 0.0, 0.2], root_quat=motion.root_quat,
                  dof_pos=motion.dof_pos)
    np.testing.assert_array_equal(plant_supporting_feet(high, model).dof_pos, high.dof_pos)


def test_only_the_foot_under_the_centre_of_pressure_is_stood_on():
    """Accelerating sideways at a = g d / z (d: the centre of mass's distance from the right
    sole's centre, z its height) puts the centre of pressure under the right foot (see the rigid
    acceleration test above): the right foot comes down, the left one carries nothing and keeps
    its height."""
    model = build_humanoid(HumanoidConfig())
    still = _crouched(3)
    com = _centre_of_mass(still, 1)
    data = mujoco.MjData(model)
    data.qpos[:] = still.qpos()[1]
    mujoco.mj_kinematics(model, data)
    right = data.xpos[[model.body("R_Ankle").id, model.body("R_Toe").id], 1].mean()
    sole = side_sole_heights(still, model)[0]
    a = GRAVITY * (com[1] - right) / (com[2] - sole.min())
    t = np.arange(30) / 30.0
    motion = _crouched(30, root_y=0.5 * a * t**2)
    planted = plant_supporting_feet(motion, model)
    before, after = side_sole_heights(motion, model), side_sole_heights(planted, model)
    inner = slice(2, -2)  # the end frames' accelerations are not measured
    assert np.all((after[inner, 1] >= -1e-4) & (after[inner, 1] <= 3e-3))
    np.testing.assert_allclose(after[inner, 0], before[inner, 0], atol=1e-9)


def test_a_walk_planned_on_its_feet_is_barely_changed():
    """The bundled walk keeps its centre of pressure inside its planted feet: what standing on the
    supporting feet changes is a swing foot's last centimetre at lift-off or touchdown. Nothing is
    raised, nothing goes below the floor and the pelvis does not move."""
    model = build_humanoid(HumanoidConfig())
    walk = Motion.load(Path(__file__).parents[1] / "assets" / "clips" / "flat_walk" / "motion.npz")
    planted = plant_supporting_feet(walk, model)
    before, after = side_sole_heights(walk, model), side_sole_heights(planted, model)
    assert np.all(after <= before + 1e-5) and np.all(after >= -1e-4)  # the leg solver's tolerance: 10 µm
    assert np.abs(after - before).max() < 0.01
    np.testing.assert_array_equal(planted.root_pos, walk.in_humanoid_order().root_pos)
