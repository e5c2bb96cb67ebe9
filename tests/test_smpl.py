"""SMPL axis-angle parameters <-> humanoid motions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, build_humanoid, joint_range_deg
from crisp_gym.motion import Motion, compute_kinematics
from crisp_gym.smpl import load_smpl_params, save_smpl_params

# SMPL's 23 non-root joints in body_pose order.
SMPL_POSE_JOINTS = ["L_Hip", "R_Hip", "Spine1", "L_Knee", "R_Knee", "Spine2", "L_Ankle", "R_Ankle", "Spine3",
                    "L_Foot", "R_Foot", "Neck", "L_Collar", "R_Collar", "Head", "L_Shoulder", "R_Shoulder",
                    "L_Elbow", "R_Elbow", "L_Wrist", "R_Wrist", "L_Hand", "R_Hand"]


@pytest.fixture(scope="module")
def model():
    return build_humanoid()


def params(t: int = 4, **joints: tuple[int, float]) -> dict[str, np.ndarray]:
    """Zero SMPL parameters with ``joint=(smpl axis, degrees)`` rotations on some joints."""
    pose = np.zeros((t, 23, 3))
    for joint, (axis, degrees) in joints.items():
        pose[:, SMPL_POSE_JOINTS.index(joint), axis] = np.deg2rad(degrees)
    return {"global_orient": np.zeros((t, 3)), "body_pose": pose.reshape(t, 69), "transl": np.zeros((t, 3))}


def smooth_motion(t: int = 40, seed: int = 0) -> Motion:
    """A smooth motion inside the joint ranges, walking forward while turning."""
    rng = np.random.default_rng(seed)
    ranges = np.deg2rad(np.concatenate([joint_range_deg(b) for b in BODY_NAMES[1:]]))
    mid, half = ranges.mean(1), np.diff(ranges, axis=1)[:, 0] / 2
    phase = rng.uniform(0, 2 * np.pi, len(DOF_NAMES))
    s = np.linspace(0, 2 * np.pi, t)[:, None]
    dof = mid + 0.5 * np.minimum(half, np.deg2rad(70)) * np.sin(s + phase)
    yaw = np.linspace(0, 1.5, t)
    quat = Rotation.from_euler("ZYX", np.column_stack([yaw, 0.2 * np.sin(yaw), 0.1 * np.cos(yaw)])).as_quat(
        scalar_first=True)
    pos = np.column_stack([np.linspace(0, 2, t), 0.3 * np.sin(yaw), 0.9 + 0.05 * np.cos(3 * yaw)])
    return Motion(fps=50.0, root_pos=pos, root_quat=quat, dof_pos=dof)


def test_round_trip_through_smpl_parameters(tmp_path, model):
    motion = smooth_motion()
    path = save_smpl_params(motion, tmp_path / "smpl.npz")
    with np.load(path) as data:
        assert data["body_pose"].shape == (motion.num_frames, 69)
        assert data["global_orient"].shape == data["transl"].shape == (motion.num_frames, 3)
        # y-up world: SMPL's y is our height, its z our forward axis
        np.testing.assert_allclose(data["transl"][:, 1], motion.root_pos[:, 2])
        np.testing.assert_allclose(data["transl"][:, 2], motion.root_pos[:, 0])
    back = load_smpl_params(path, to_floor=False)
    assert back.fps == motion.fps
    np.testing.assert_allclose(back.dof_pos, motion.dof_pos, atol=1e-9)
    np.testing.assert_allclose(back.root_pos, motion.root_pos, atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(back.root_quat * motion.root_quat, axis=1)), 1.0, atol=1e-12)
    grounded = load_smpl_params(path, model=model)
    np.testing.assert_allclose(grounded.root_pos[:, :2], motion.root_pos[:, :2], atol=1e-12)
    assert np.ptp(grounded.root_pos[:, 2] - motion.root_pos[:, 2]) < 1e-12


def test_left_knee_flexion_lands_on_l_knee_y_and_moves_the_shank_back(model):
    motion = load_smpl_params(params(L_Knee=(0, 60.0)))
    expected = np.zeros(len(DOF_NAMES))
    expected[DOF_NAMES.index("L_Knee_y")] = np.deg2rad(60.0)
    np.testing.assert_allclose(motion.dof_pos, np.tile(expected, (4, 1)), atol=1e-12)
    body = compute_kinematics(motion, model).body_pos[0]
    shank = body[BODY_NAMES.index("L_Ankle")] - body[BODY_NAMES.index("L_Knee")]
    c, s = np.cos(np.radians(60)), np.sin(np.radians(60))
    np.testing.assert_allclose(shank / np.linalg.norm(shank), [-s, 0.0, -c], atol=1e-9)


def test_hip_flexion_moves_the_thigh_forward(model):
    # SMPL: a negative rotation about x swings the leg (pointing -y) towards +z, the facing.
    motion = load_smpl_params(params(L_Hip=(0, -30.0)))
    assert np.rad2deg(motion.dof_pos[0, DOF_NAMES.index("L_Hip_y")]) == pytest.approx(-30.0)
    body = compute_kinematics(motion, model).body_pos[0]
    thigh = body[BODY_NAMES.index("L_Knee")] - body[BODY_NAMES.index("L_Hip")]
    np.testing.assert_allclose(thigh / np.linalg.norm(thigh), [0.5, 0.0, -np.sqrt(3) / 2], atol=1e-9)


# SMPL's body axes (x left, y up, z forward) are our y, z and x (x forward, y left, z up).
@pytest.mark.parametrize("joint, axis, dof", [
    ("Spine1", 0, "Torso_y"), ("Spine2", 2, "Spine_x"), ("Spine3", 1, "Chest_z"),
    ("L_Collar", 2, "L_Thorax_x"), ("R_Foot", 0, "R_Toe_y"), ("Head", 1, "Head_z"),
    ("R_Shoulder", 2, "R_Shoulder_x"), ("L_Hand", 1, "L_Hand_z"),
])  # fmt: skip
def test_joints_map_by_name(joint, axis, dof):
    motion = load_smpl_params(params(**{joint: (axis, 25.0)}), to_floor=False)
    nonzero = [DOF_NAMES[i] for i in np.flatnonzero(np.abs(motion.dof_pos[0]) > 1e-12)]
    assert nonzero == [dof]
    assert np.rad2deg(motion.dof_pos[0, DOF_NAMES.index(dof)]) == pytest.approx(25.0)


def test_63_wide_body_pose_leaves_the_hands_at_rest():
    full = params(L_Elbow=(1, -40.0), R_Wrist=(2, 10.0))
    short = dict(full, body_pose=full["body_pose"][:, :63])
    a, b = load_smpl_params(full, to_floor=False), load_smpl_params(short, to_floor=False)
    np.testing.assert_allclose(a.dof_pos, b.dof_pos)


def test_y_up_and_z_up_inputs_give_the_same_motion(model):
    rng = np.random.default_rng(1)
    t = 6
    y_up = {"global_orient": rng.normal(scale=0.5, size=(t, 3)),
            "body_pose": rng.normal(scale=0.2, size=(t, 69)),
            "transl": rng.normal(size=(t, 3))}
    # The same motion in a z-up world (SMPL's y -> z, z -> x, x -> y).
    to_z = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    z_up = dict(y_up, transl=y_up["transl"] @ to_z.T,
                global_orient=(Rotation.from_matrix(to_z) * Rotation.from_rotvec(y_up["global_orient"])).as_rotvec())
    a = load_smpl_params(y_up, up_axis="y", model=model)
    b = load_smpl_params(z_up, up_axis="z", model=model)
    np.testing.assert_allclose(a.root_pos, b.root_pos, atol=1e-9)
    np.testing.assert_allclose(a.dof_pos, b.dof_pos, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(a.root_quat * b.root_quat, axis=1)), 1.0, atol=1e-9)
    # ... and in both the body stands up: the pelvis-to-chest axis of a zero pose is +z.
    upright = load_smpl_params(params(), up_axis="y", model=model)
    body = compute_kinematics(upright, model).body_pos[0]
    assert body[BODY_NAMES.index("Head"), 2] > body[BODY_NAMES.index("Pelvis"), 2] + 0.3


@pytest.mark.parametrize("change, message", [
    (lambda p: p.pop("transl"), "lack"),
    (lambda p: p.update(body_pose=p["body_pose"][:, :60]), "body_pose must have shape"),
    (lambda p: p.update(transl=p["transl"][:3]), "transl must have shape"),
    (lambda p: p["global_orient"].__setitem__((2, 1), np.nan), "global_orient has non-finite values .*frame 2"),
    (lambda p: p.update({k: v[:1] for k, v in p.items()}), "at least 2 frames"),
    (lambda p: p.update(body_pose=np.array([["a"] * 69] * 4)), "numeric"),
    (lambda p: p.update(global_orient=p["global_orient"] + 1j), "global_orient must be a real numeric array"),
])  # fmt: skip
def test_bad_parameters_are_rejected(change, message):
    p = params()
    change(p)
    with pytest.raises(ValueError, match=message):
        load_smpl_params(p)


def test_bad_sources_are_rejected(tmp_path):
    with pytest.raises(FileNotFoundError, match="no SMPL parameter file"):
        load_smpl_params(tmp_path / "missing.npz")
    np.save(tmp_path / "single.npy", np.zeros((4, 3)))
    with pytest.raises(ValueError, match="single array"):
        load_smpl_params(tmp_path / "single.npy")
    (tmp_path / "text.npz").write_text("not an archive")
    with pytest.raises(ValueError, match="not a readable npz"):
        load_smpl_params(tmp_path / "text.npz")
    with pytest.raises(ValueError, match="up_axis"):
        load_smpl_params(params(), up_axis="x")
