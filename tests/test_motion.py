from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import approx_fprime
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, build_humanoid, joint_range_deg
from crisp_gym.motion import (
    Motion,
    _RotationDistance,
    compute_kinematics,
    fit_hinges_into_range,
    foot_sole_heights,
    ground,
    hinge_angles_to_rotations,
    level_feet,
    low_pass_joints,
    plant_feet,
    planted_feet,
    rotations_to_hinge_angles,
    side_sole_heights,
)
from tests.conftest import fold_leg, sway_motion


def _random_motion(frames=20, seed=0) -> Motion:
    rng = np.random.default_rng(seed)
    quats = Rotation.from_rotvec(rng.normal(0, 0.3, (frames, 3))).as_quat(scalar_first=True)
    return Motion(fps=30, root_pos=rng.normal(0, 1, (frames, 3)), root_quat=quats,
                  dof_pos=rng.normal(0, 0.3, (frames, 69)), contacts=rng.random((frames, 24)) > 0.5)


def test_npz_round_trip_and_reordering(tmp_path):
    motion = _random_motion()
    # write with a shuffled hinge order: loading must put every column back by name
    perm = np.random.default_rng(1).permutation(69)
    shuffled = Motion(fps=motion.fps, root_pos=motion.root_pos, root_quat=motion.root_quat,
                      dof_pos=motion.dof_pos[:, perm], dof_names=tuple(np.array(DOF_NAMES)[perm]),
                      contacts=motion.contacts)
    loaded = Motion.load(shuffled.save(tmp_path / "motion.npz"))
    np.testing.assert_array_equal(loaded.dof_pos, motion.dof_pos)
    np.testing.assert_array_equal(loaded.contacts, motion.contacts)
    assert loaded.dof_names == DOF_NAMES and loaded.body_names == BODY_NAMES
    with np.load(tmp_path / "motion.npz") as data:
        assert int(data["format_version"]) == 1 and data["dof_pos"].shape == (20, 69)
    assert not list(tmp_path.glob("*.tmp"))


@pytest.mark.parametrize("change, message", [
    (dict(fps=0), "fps"),
    (dict(root_pos=np.full((20, 3), np.nan)), "non-finite"),
    (dict(root_quat=np.tile([2.0, 0, 0, 0], (20, 1))), "unit quaternions"),
    (dict(dof_pos=np.zeros((20, 68))), "dof_pos"),
    (dict(dof_names=DOF_NAMES[:-1]), "dof_names"),
])
def test_validation_errors(change, message):
    base = _random_motion()
    fields = dict(fps=base.fps, root_pos=base.root_pos, root_quat=base.root_quat, dof_pos=base.dof_pos)
    fields.update(change)
    with pytest.raises(ValueError, match=message):
        Motion(**fields)


def test_load_rejects_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        Motion.load(tmp_path / "absent.npz")
    np.savez(tmp_path / "bad.npz", fps=30.0, root_pos=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="missing"):
        Motion.load(tmp_path / "bad.npz")


def test_hinge_angle_conversion_is_continuous_past_90_degrees():
    t = np.linspace(0, 1, 80)
    angles = np.zeros((80, 2, 3))
    angles[:, 0, 1] = 2.6 * t  # knee-like flexion to 150 degrees
    angles[:, 1] = np.c_[0.4 * np.sin(6 * t), 1.4 * t, -0.5 * t]
    recovered = rotations_to_hinge_angles(hinge_angles_to_rotations(angles))
    np.testing.assert_allclose(recovered, angles, atol=1e-9)


def test_fitting_into_range_finds_the_in_range_triple_of_a_rotation_clipping_turns_away():
    # Every rotation has two XYZ triples, (a, b, c) and (a + 180, 180 - b, c + 180). Near b = -90°
    # (a hip flexed to the horizontal) a capture can come out as the second, far outside the range.
    ranges = np.deg2rad(np.array([joint_range_deg("L_Hip")]))  # (1, 3, 2)
    inside = np.deg2rad([[[-20.0, -88.0, 10.0]], [[-25.0, -60.0, 5.0]]])  # (2 frames, 1 joint, 3)
    outside = inside.copy()
    outside[0, 0] = np.deg2rad([160.0, -92.0, -170.0])
    np.testing.assert_allclose(hinge_angles_to_rotations(outside), hinge_angles_to_rotations(inside), atol=1e-12)

    def turn_deg(a, b):
        r = Rotation.from_matrix(hinge_angles_to_rotations(a).reshape(-1, 3, 3))
        return np.rad2deg((r.inv() * Rotation.from_matrix(hinge_angles_to_rotations(b).reshape(-1, 3, 3))).magnitude())

    fitted = fit_hinges_into_range(outside, ranges)
    assert np.all((fitted >= ranges[..., 0] - 1e-12) & (fitted <= ranges[..., 1] + 1e-12))
    assert turn_deg(fitted, outside).max() < 0.5
    np.testing.assert_array_equal(fitted[1], outside[1])  # a frame already in range is kept as it is
    assert turn_deg(np.clip(outside, ranges[..., 0], ranges[..., 1]), outside)[0] > 90.0


@pytest.mark.parametrize("seed", range(5))
def test_the_range_fit_cost_and_gradient_agree_with_rotations_and_finite_differences(seed):
    """The fit's written-out cost is the squared distance of :func:`hinge_angles_to_rotations`'
    matrices plus the continuity term, and its gradient that of finite differences."""
    rng = np.random.default_rng(seed)
    target = Rotation.random(random_state=seed).as_matrix()
    previous, x = rng.uniform(-np.pi, np.pi, (2, 3))
    cost = _RotationDistance(target, previous, continuity=0.3)
    value, gradient = cost(x)
    expected = np.sum((hinge_angles_to_rotations(x) - target) ** 2) + 0.3 * np.sum((x - previous) ** 2)
    assert value == pytest.approx(expected, abs=1e-12)
    np.testing.assert_allclose(gradient, approx_fprime(x, lambda y: cost(y)[0], 1e-7), atol=1e-5)


def test_resample_matches_analytic_motion():
    fps = 30.0
    t = np.arange(31) / fps
    yaw = 0.8 * t
    quats = Rotation.from_euler("z", yaw[:, None]).as_quat(scalar_first=True)
    dof = np.outer(t, np.ones(69)) * 0.1
    motion = Motion(fps=fps, root_pos=np.c_[t, 2 * t, np.ones_like(t)], root_quat=quats, dof_pos=dof)
    fine = motion.resample(120.0)
    t_new = np.arange(fine.num_frames) / 120.0
    assert fine.num_frames == 121 and fine.duration == pytest.approx(motion.duration)
    np.testing.assert_allclose(fine.root_pos[:, 1], 2 * t_new, atol=1e-12)
    np.testing.assert_allclose(Rotation.from_quat(fine.root_quat, scalar_first=True).as_euler("xyz")[:, 2],
                               0.8 * t_new, atol=1e-9)  # slerp of a constant-rate yaw is exact
    np.testing.assert_allclose(fine.dof_pos[:, 5], 0.1 * t_new, atol=1e-12)


def test_kinematics_velocities_match_motion():
    model = build_humanoid()
    motion = sway_motion(frames=40)
    kin = compute_kinematics(motion, model)
    # the pelvis drifts at 0.1 m/s in x; its angular velocity is zero
    np.testing.assert_allclose(kin.body_lin_vel[5:-5, 0], [[0.1, 0, 0]] * 30, atol=1e-9)
    np.testing.assert_allclose(kin.body_ang_vel[:, 0], 0.0, atol=1e-9)
    # the left knee's hinge rate equals the shank's angular speed about the y axis
    knee = BODY_NAMES.index("L_Knee")
    rate = np.gradient(motion.dof_pos[:, DOF_NAMES.index("L_Knee_y")], 1 / 30)
    hip_rate = np.gradient(motion.dof_pos[:, DOF_NAMES.index("L_Hip_y")], 1 / 30)
    np.testing.assert_allclose(kin.body_ang_vel[2:-2, knee, 1], (rate + hip_rate)[2:-2], atol=2e-3)


def test_ground_puts_the_lowest_foot_on_the_floor():
    model = build_humanoid()
    motion = sway_motion().translated([0, 0, 0.3])
    grounded = ground(motion, model, floor_height=0.1)
    soles = foot_sole_heights(grounded, model)
    assert np.percentile(soles, 5) == pytest.approx(0.1, abs=1e-9)
    np.testing.assert_allclose(grounded.root_pos[:, :2], motion.root_pos[:, :2])


def _body_axes(motion: Motion, model, body: str) -> np.ndarray:
    """(T, 3, 3) world rotation of ``body``; its columns are the body's x, y, z axes."""
    quat = compute_kinematics(motion, model).body_quat[:, BODY_NAMES.index(body)]
    return Rotation.from_quat(quat, scalar_first=True).as_matrix()


def test_level_feet_flattens_planted_feet_only():
    """Standing still on a left sole rolled 15° (turned out 20°) with toes curled 40°, while the
    right leg swings fast with its sole rolled 10°: the planted left foot comes out level across,
    still turned out, and its toes level; the swinging foot keeps its roll and gets straight toes.
    No joint but the toes moves."""
    model = build_humanoid()
    frames = 60
    t = np.arange(frames) / 30.0
    dof = np.zeros((frames, len(DOF_NAMES)))
    col = {name: DOF_NAMES.index(name) for name in DOF_NAMES}
    dof[:, col["L_Ankle_x"]] = np.radians(15.0)
    dof[:, col["L_Hip_z"]] = np.radians(20.0)  # the leg turned out
    dof[:, [col["L_Toe_y"], col["R_Toe_y"]]] = np.radians(40.0)
    dof[:, col["R_Hip_x"]] = -0.5 * np.cos(2 * np.pi * t)  # the leg circles: the foot never stops
    dof[:, col["R_Hip_y"]] = 0.5 * np.sin(2 * np.pi * t)
    dof[:, col["R_Ankle_x"]] = np.radians(-10.0)
    motion = Motion(fps=30.0, root_pos=np.tile([0.0, 0.0, 1.0], (frames, 1)),
                    root_quat=np.tile([1.0, 0, 0, 0], (frames, 1)), dof_pos=dof)
    assert planted_feet(motion, model)[:, 0].all() and not planted_feet(motion, model)[:, 1].any()
    level = level_feet(motion, model)

    foot = _body_axes(level, model, "L_Ankle")
    np.testing.assert_allclose(foot[:, 2], [[0.0, 0.0, 1.0]] * frames, atol=1e-9)  # sole normal up
    heading = np.degrees(np.arctan2(foot[:, 1, 0], foot[:, 0, 0]))
    np.testing.assert_allclose(heading, 20.0, atol=1e-6)  # turned out as before
    np.testing.assert_allclose(_body_axes(level, model, "L_Toe")[:, 2], [[0.0, 0.0, 1.0]] * frames, atol=1e-9)

    np.testing.assert_allclose(_body_axes(level, model, "R_Ankle"), _body_axes(motion, model, "R_Ankle"), atol=1e-9)
    np.testing.assert_allclose(level.dof_pos[:, [col["R_Toe_x"], col["R_Toe_y"], col["R_Toe_z"]]], 0.0, atol=1e-9)

    moved = compute_kinematics(level, model).body_pos - compute_kinematics(motion, model).body_pos
    toes = [BODY_NAMES.index("L_Toe"), BODY_NAMES.index("R_Toe")]
    np.testing.assert_allclose(np.delete(moved, toes, axis=1), 0.0, atol=1e-12)


def _standing_on_the_right(lift: np.ndarray) -> Motion:
    """Standing on the right foot while the left leg folds by ``lift`` (T,) radians at the hip and
    knee and back at the ankle: the left foot stays level and rises (3.7 cm at 0.3 rad)."""
    dof = np.zeros((len(lift), len(DOF_NAMES)))
    fold_leg(dof, "L", lift)
    motion = Motion(fps=30.0, root_pos=np.tile([0.0, 0.0, 1.0], (len(lift), 1)),
                    root_quat=np.tile([1.0, 0, 0, 0], (len(lift), 1)), dof_pos=dof)
    return ground(motion, build_humanoid(), percentile=0.0)


def test_plant_feet_brings_a_hovering_planted_foot_down():
    """A left foot held still 3.7 cm above the floor beside the standing right one comes down onto
    the floor: straight down (its orientation and horizontal place kept), by unbending that leg's
    hip and knee; the right leg, the pelvis and everything else stay as they were."""
    model = build_humanoid()
    motion = _standing_on_the_right(np.full(30, 0.3))
    sole = side_sole_heights(motion, model)
    assert planted_feet(motion, model).all() and np.all(sole[:, 0] > 0.03) and np.allclose(sole[:, 1], 0.0)
    planted = plant_feet(motion, model)

    after = side_sole_heights(planted, model)
    assert np.all((after[:, 0] >= -1e-4) & (after[:, 0] <= 3e-3))  # it leaves 2 mm alone
    np.testing.assert_allclose(after[:, 1], 0.0, atol=1e-9)
    foot = BODY_NAMES.index("L_Ankle")
    before_kin, after_kin = compute_kinematics(motion, model), compute_kinematics(planted, model)
    np.testing.assert_allclose(_body_axes(planted, model, "L_Ankle"), _body_axes(motion, model, "L_Ankle"), atol=1e-6)
    np.testing.assert_allclose(after_kin.body_pos[:, foot, :2], before_kin.body_pos[:, foot, :2], atol=1e-4)
    assert np.all(planted.dof_pos[:, DOF_NAMES.index("L_Knee_y")] < motion.dof_pos[:, DOF_NAMES.index("L_Knee_y")])
    left_leg = [DOF_NAMES.index(f"L_{b}_{a}") for b in ("Hip", "Knee", "Ankle") for a in "xyz"]
    others = np.delete(planted.dof_pos, left_leg, axis=1)
    np.testing.assert_array_equal(others, np.delete(motion.dof_pos, left_leg, axis=1))
    np.testing.assert_array_equal(planted.root_pos, motion.root_pos)


def test_plant_feet_fades_out_into_the_swing_and_leaves_feet_on_the_floor_alone():
    """The left foot hovers 3.7 cm for a second, then rises into a swing: planted frames come down,
    the correction fades out linearly over ``plant_blend`` (0.1 s) after the stance, swing frames
    beyond it are untouched, and a clip whose planted feet stand on the floor moves by less than
    0.1 mm."""
    model = build_humanoid()
    lift = np.r_[np.full(30, 0.3), 0.3 + 0.6 * np.sin(np.linspace(0, np.pi / 2, 30)) ** 2]
    motion = _standing_on_the_right(lift)
    on = planted_feet(motion, model)[:, 0]
    assert on[:25].all() and not on[40:].any()
    planted = plant_feet(motion, model)
    before, after = side_sole_heights(motion, model)[:, 0], side_sole_heights(planted, model)[:, 0]
    assert np.all(after[on] <= 3e-3) and np.all(after >= -1e-4)
    last = np.flatnonzero(on)[-1]
    np.testing.assert_array_equal(planted.dof_pos[last + 4:], motion.dof_pos[last + 4:])  # 0.1 s at 30 fps
    correction = after - before
    assert np.abs(np.diff(correction)).max() <= np.abs(correction).max() / 3 + 1e-3  # fades over 3 frames
    # the bundled walk's planted feet stand on the floor to within the 2 mm left alone (one at 2.05)
    flat = Motion.load(Path(__file__).parents[1] / "assets" / "clips" / "flat_walk" / "motion.npz")
    moved = compute_kinematics(plant_feet(flat, model), model).body_pos - compute_kinematics(flat, model).body_pos
    assert np.abs(moved).max() < 1e-4


def test_low_pass_joints_keeps_slow_motion_and_removes_flicker():
    fps, frames = 120.0, 480
    t = np.arange(frames) / fps
    slow = 0.5 * np.sin(2 * np.pi * 1.0 * t)  # a 1 Hz arm swing
    flicker = 0.2 * np.sin(2 * np.pi * 25.0 * t)  # marker noise
    dof = np.zeros((frames, len(DOF_NAMES)))
    dof[:, DOF_NAMES.index("R_Wrist_z")] = slow + flicker
    motion = Motion(fps=fps, root_pos=np.zeros((frames, 3)), root_quat=np.tile([1.0, 0, 0, 0], (frames, 1)),
                    dof_pos=dof)
    filtered = low_pass_joints(motion, 6.0).dof_pos[:, DOF_NAMES.index("R_Wrist_z")]
    inner = slice(60, -60)  # away from the ends' padding
    np.testing.assert_allclose(filtered[inner], slow[inner], atol=0.01)  # 25 Hz: down by > 95 %
    np.testing.assert_array_equal(low_pass_joints(motion, 6.0).root_pos, motion.root_pos)
    assert low_pass_joints(motion, 100.0) is motion  # above Nyquist: nothing to remove
    with pytest.raises(ValueError, match="positive frequency"):
        low_pass_joints(motion, 0.0)
