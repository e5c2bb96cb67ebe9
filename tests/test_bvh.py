"""BVH parsing, forward kinematics and retargeting onto the humanoid."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crisp_gym.bvh import JOINT_MAPS, bvh_forward_kinematics, load_bvh, parse_bvh, retarget_bvh
from crisp_gym.clip import write_clip
from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, build_humanoid, default_rest_joints, joint_range_deg
from crisp_gym.import_motion import read_motion
from crisp_gym.motion import (
    Motion,
    StanceGrounding,
    compute_kinematics,
    foot_sole_heights,
    ground_stance,
    planted_feet,
    side_sole_heights,
    stance_floor,
)
from crisp_gym.scene import floor_box
from tests.conftest import SHARED_DATA

CMU_DIR = SHARED_DATA / "cmu_bvh"
CMU_CLIPS = ("131_01", "131_02", "131_03")
CMU_UNIT = 0.0254 / 0.45  # CMU's ASF length unit: 1/0.45 inch
# BVH axes of the synthetic files (y up, facing +z, left +x) in ours (z up, facing +x, left +y).
BVH_TO_OURS = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@pytest.fixture(scope="module")
def model():
    return build_humanoid()


# --- a BVH writer for synthetic files -------------------------------------------------------


def write_bvh(path: Path, joints: list[tuple], rotations: np.ndarray, root_pos: np.ndarray,
              order: str = "ZXY", frame_time: float = 1 / 30) -> Path:
    """Write joints [(name, parent, offset, end_site or None)] with (T, J, 3, 3) local rotations."""
    names = [j[0] for j in joints]
    children = {n: [j[0] for j in joints if j[1] == n] for n in names}
    rot_channels = " ".join(f"{a}rotation" for a in order)
    lines = ["HIERARCHY"]

    def emit(k: int, depth: int) -> None:
        name, parent, offset, end = joints[k]
        pad = "  " * depth
        lines.append(f"{pad}{'ROOT' if parent is None else 'JOINT'} {name}")
        lines.append(pad + "{")
        lines.append(f"{pad}  OFFSET {offset[0]:.6f} {offset[1]:.6f} {offset[2]:.6f}")
        pos = "Xposition Yposition Zposition " if parent is None else ""
        lines.append(f"{pad}  CHANNELS {6 if parent is None else 3} {pos}{rot_channels}")
        for child in children[name]:
            emit(names.index(child), depth + 1)
        if end is not None:
            lines.extend([f"{pad}  End Site", pad + "  {",
                          f"{pad}    OFFSET {end[0]:.6f} {end[1]:.6f} {end[2]:.6f}", pad + "  }"])
        lines.append(pad + "}")

    emit(0, 0)
    t = rotations.shape[0]
    lines += ["MOTION", f"Frames: {t}", f"Frame Time: {frame_time:.8f}"]
    for k in range(t):
        row = list(root_pos[k])
        # channel values must follow the file's (depth-first) joint order
        for name in _depth_first(names, children):
            angles = Rotation.from_matrix(rotations[k, names.index(name)]).as_euler(order, degrees=True)
            row += list(angles)
        lines.append(" ".join(f"{v:.9f}" for v in row))
    path.write_text("\n".join(lines) + "\n")
    return path


def _depth_first(names: list[str], children: dict[str, list[str]]) -> list[str]:
    out: list[str] = []
    stack = [names[0]]
    while stack:
        n = stack.pop()
        out.append(n)
        stack.extend(reversed(children[n]))
    return out


# The 31-joint CMU (cgspeed) skeleton: joint -> (parent, the body of ours whose rest joint it sits
# at, End Site offset in our axes or None).
CGSPEED = {
    "Hips": (None, "Pelvis", None), "LHipJoint": ("Hips", "Pelvis", None),
    "LeftUpLeg": ("LHipJoint", "L_Hip", None), "LeftLeg": ("LeftUpLeg", "L_Knee", None),
    "LeftFoot": ("LeftLeg", "L_Ankle", None), "LeftToeBase": ("LeftFoot", "L_Toe", (0.05, 0, 0)),
    "RHipJoint": ("Hips", "Pelvis", None), "RightUpLeg": ("RHipJoint", "R_Hip", None),
    "RightLeg": ("RightUpLeg", "R_Knee", None), "RightFoot": ("RightLeg", "R_Ankle", None),
    "RightToeBase": ("RightFoot", "R_Toe", (0.05, 0, 0)),
    "LowerBack": ("Hips", "Torso", None), "Spine": ("LowerBack", "Spine", None),
    "Spine1": ("Spine", "Chest", None), "Neck": ("Spine1", "Chest", None),
    "Neck1": ("Neck", "Neck", None), "Head": ("Neck1", "Head", (0, 0, 0.1)),
    "LeftShoulder": ("Spine1", "L_Thorax", None), "LeftArm": ("LeftShoulder", "L_Shoulder", None),
    "LeftForeArm": ("LeftArm", "L_Elbow", None), "LeftHand": ("LeftForeArm", "L_Wrist", None),
    "LeftFingerBase": ("LeftHand", "L_Hand", None), "LeftHandIndex1": ("LeftFingerBase", "L_Hand+", (0, 0.02, 0)),
    "LThumb": ("LeftHand", "L_Wrist+", (0.02, 0, 0)),
    "RightShoulder": ("Spine1", "R_Thorax", None), "RightArm": ("RightShoulder", "R_Shoulder", None),
    "RightForeArm": ("RightArm", "R_Elbow", None), "RightHand": ("RightForeArm", "R_Wrist", None),
    "RightFingerBase": ("RightHand", "R_Hand", None), "RightHandIndex1": ("RightFingerBase", "R_Hand+", (0, -0.02, 0)),
    "RThumb": ("RightHand", "R_Wrist+", (0.02, 0, 0)),
}  # fmt: skip
# "<body>+" marks a point a little beyond the body's joint (fingers, thumb).
_BEYOND = {"L_Hand+": (0, 0.03, 0), "R_Hand+": (0, -0.03, 0), "L_Wrist+": (0.02, 0.01, 0),
           "R_Wrist+": (0.02, -0.01, 0)}
MIXAMO_NAMES = {"LHipJoint": None, "RHipJoint": None, "LowerBack": "Spine", "Spine": "Spine1",
                "Spine1": "Spine2", "Neck": None, "Neck1": "Neck", "LeftFingerBase": "LeftHandMiddle1",
                "RightFingerBase": "RightHandMiddle1", "LeftHandIndex1": "LeftHandMiddle2",
                "RightHandIndex1": "RightHandMiddle2", "LThumb": "LeftHandThumb1", "RThumb": "RightHandThumb1"}


def cgspeed_joints(unit: float, to_file: np.ndarray, rename: dict | None = None,
                   bend_rest: bool = False) -> list[tuple]:
    """The skeleton with our rest proportions, in file units and axes (our vector v -> to_file @ v).

    ``bend_rest`` makes a non-T-pose rest: arms hanging down, legs 10° apart (CMU-like).
    ``rename`` maps joint names to new ones, or to None to leave the joint out. Returns the joint
    list for :func:`write_bvh`.
    """
    rest = default_rest_joints(1.70)
    pos = {}
    for name, (_, at, _) in CGSPEED.items():
        base = at.rstrip("+")
        pos[name] = rest[BODY_NAMES.index(base)] + np.array(_BEYOND.get(at, (0, 0, 0)))
    ends = {n: np.array(e, dtype=float) for n, (_, _, e) in CGSPEED.items() if e is not None}
    if bend_rest:
        for side, s in (("Left", 1), ("Right", -1)):
            down = Rotation.from_euler("x", -90 * s, degrees=True)  # arm from +-y to -z
            pivot = pos[f"{side}Arm"]
            for part in (f"{side}ForeArm", f"{side}Hand", f"{side}FingerBase", f"{side}HandIndex1",
                         f"{side[0]}Thumb"):
                pos[part] = pivot + down.apply(pos[part] - pivot)
            for part in (f"{side}HandIndex1", f"{side[0]}Thumb"):
                ends[part] = down.apply(ends[part])
            spread = Rotation.from_euler("x", 10 * s, degrees=True)  # leg 10 degrees outwards
            hip = pos[f"{side}UpLeg"]
            for part in (f"{side}Leg", f"{side}Foot", f"{side}ToeBase"):
                pos[part] = hip + spread.apply(pos[part] - hip)
    rename = rename or {}
    kept = [n for n in CGSPEED if rename.get(n, n) is not None]

    def kept_parent(n: str) -> str | None:
        p = CGSPEED[n][0]
        while p is not None and rename.get(p, p) is None:
            p = CGSPEED[p][0]
        return p

    joints = []
    for n in kept:
        p = kept_parent(n)
        offset = pos[n] - (pos[p] if p is not None else 0.0)
        end = to_file @ ends[n] / unit if n in ends else None
        joints.append((rename.get(n, n), None if p is None else rename.get(p, p), to_file @ offset / unit, end))
    return joints


# Known poses, as rotations in OUR axes of the joint that drives each body: the retargeted hinge
# angles must come back as exactly these (single-axis ones, and one XYZ triple for the left hip).
POSES = [
    {},
    {"L_Knee": ("y", 40.0), "R_Hip": ("y", -30.0), "L_Shoulder": ("x", 45.0), "Spine": ("z", 20.0),
     "L_Elbow": ("z", -30.0)},  # elbow flexion is negative z on the left
    {"L_Hip": ("XYZ", (10.0, -20.0, 15.0)), "R_Knee": ("y", 70.0), "R_Shoulder": ("z", -50.0),
     "Head": ("x", 15.0), "L_Ankle": ("y", 20.0)},
]
ROOT_YAW_DEG = [0.0, 30.0, -20.0]
ROOT_XY = [(0.0, 0.0), (0.4, -0.2), (0.9, 0.1)]
CGSPEED_OF_BODY = {"Pelvis": "Hips", "L_Hip": "LeftUpLeg", "L_Knee": "LeftLeg", "L_Ankle": "LeftFoot",
                   "R_Hip": "RightUpLeg", "R_Knee": "RightLeg", "Spine": "Spine", "Head": "Head",
                   "L_Shoulder": "LeftArm", "R_Shoulder": "RightArm", "L_Elbow": "LeftForeArm"}


def expected_dofs() -> np.ndarray:
    out = np.zeros((len(POSES), len(DOF_NAMES)))
    for k, pose in enumerate(POSES):
        for body, (axes, angles) in pose.items():
            angles = np.atleast_1d(angles)
            for axis, angle in zip(axes.lower(), angles):
                out[k, DOF_NAMES.index(f"{body}_{axis}")] = np.deg2rad(angle)
    return out


def pose_rotations(names: list[str], to_file: np.ndarray, rename: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(T, J, 3, 3) file-axes local rotations and (T, 3) root positions (metres, our axes) of POSES."""
    rename = rename or {}
    t = len(POSES)
    rots = np.broadcast_to(np.eye(3), (t, len(names), 3, 3)).copy()
    root = np.zeros((t, 3))
    for k, pose in enumerate(POSES):
        items = dict(pose, Pelvis=("z", ROOT_YAW_DEG[k]))
        for body, (axes, angles) in items.items():
            ours = Rotation.from_euler(axes, angles, degrees=True).as_matrix()
            joint = rename.get(CGSPEED_OF_BODY[body], CGSPEED_OF_BODY[body])
            rots[k, names.index(joint)] = to_file @ ours @ to_file.T
        root[k] = [*ROOT_XY[k], 0.95]
    return rots, root


def bone_angles_deg(kin_pos: np.ndarray, bvh_pos: np.ndarray, pairs) -> np.ndarray:
    """(T, P) angles between our bones and the BVH's, for (our a, our b, bvh a, bvh b) index pairs."""
    out = []
    for a, b, ja, jb in pairs:
        u = kin_pos[:, b] - kin_pos[:, a]
        v = bvh_pos[:, jb] - bvh_pos[:, ja]
        cos = np.sum(u * v, axis=1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
        out.append(np.rad2deg(np.arccos(np.clip(cos, -1, 1))))
    return np.stack(out, axis=1)


# --- parsing and FK ------------------------------------------------------------------------

SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Chest
  {
    OFFSET 0 2 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 1 0
    }
  }
  JOINT Arm
  {
    OFFSET 1 0 0
    CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
    JOINT Hand
    {
      OFFSET 2 0 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 1 0 0
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.04
1 2 3 90 0 0  0 0 0  1 0 0 0 0 0  0 0 0
0 0 0 90 90 0  0 0 0  0 0 1 0 0 90  0 0 0
"""


def test_parse_small_file_and_forward_kinematics(tmp_path):
    path = tmp_path / "small.bvh"
    path.write_text(SMALL)
    clip = parse_bvh(path)
    sk = clip.skeleton
    assert sk.names == ("Hips", "Chest", "Arm", "Hand")
    assert list(sk.parents) == [-1, 0, 0, 2]
    np.testing.assert_allclose(sk.offsets, [[0, 0, 0], [0, 2, 0], [1, 0, 0], [2, 0, 0]])
    assert set(sk.end_sites) == {1, 3}
    np.testing.assert_allclose(sk.end_sites[3], [1, 0, 0])
    assert clip.num_frames == 2 and clip.fps == pytest.approx(25.0)

    rz90 = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    rx90 = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    ry90 = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    # "Zrotation Xrotation Yrotation" composes as written: Rz @ Rx @ Ry.
    np.testing.assert_allclose(clip.local_rotations[1, 0], rz90 @ rx90, atol=1e-12)
    np.testing.assert_allclose(clip.local_rotations[1, 2], ry90, atol=1e-12)
    np.testing.assert_allclose(clip.root_positions, [[1, 2, 3], [0, 0, 0]])
    # Position channels on a non-root joint replace its OFFSET.
    np.testing.assert_allclose(clip.local_translations[:, 2], [[1, 0, 0], [0, 0, 1]])

    pos, rot = bvh_forward_kinematics(clip)
    # Frame 0: Rz(90) maps x -> y, y -> -x.
    np.testing.assert_allclose(pos[0], [[1, 2, 3], [-1, 2, 3], [1, 3, 3], [1, 5, 3]], atol=1e-12)
    # Frame 1: root Rz(90) Rx(90); Chest (0,2,0) -> (0,0,2); Arm (0,0,1) -> (1,0,0);
    # Hand: Ry(90) (2,0,0) = (0,0,-2) -> root -> (-2,0,0), added to the Arm.
    np.testing.assert_allclose(pos[1], [[0, 0, 0], [0, 0, 2], [1, 0, 0], [-1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(rot[1, 3], rz90 @ rx90 @ ry90, atol=1e-12)


CHEST_CHANNELS = "CHANNELS 3 Zrotation Xrotation Yrotation\n    End"


@pytest.mark.parametrize("mutate, message", [
    (lambda s: s.rsplit("\n", 2)[0] + "\n", "declares 2 frames but has 1"),
    (lambda s: s.replace("0 0 0 90 90 0", "0 0 90 90 0"), "has 17 values"),
    (lambda s: s.replace("1 2 3 90", "1 2 abc 90"), "expected numbers"),
    (lambda s: s.replace(CHEST_CHANNELS, CHEST_CHANNELS.replace("3", "4")), "CHANNELS"),
    (lambda s: s.replace("Frame Time: 0.04", "Frame Time: fast"), "Frame Time"),
    (lambda s: s.split("MOTION")[0], "no MOTION section"),
    (lambda s: s.replace("OFFSET 0 2 0", "OFFSET 0 2"), "OFFSET"),
    (lambda s: "HIERARCHY\nMOTION\nFrames: 1\nFrame Time: 0.1\n1\n", "no ROOT"),
])  # fmt: skip
def test_bad_bvh_input_is_rejected_with_a_clear_message(tmp_path, mutate, message):
    path = tmp_path / "bad.bvh"
    path.write_text(mutate(SMALL))
    with pytest.raises(ValueError, match=message):
        parse_bvh(path)


def test_missing_bvh_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no BVH file"):
        load_bvh(tmp_path / "nope.bvh")


# --- retargeting synthetic files -----------------------------------------------------------

YAW90 = Rotation.from_euler("y", 90, degrees=True).as_matrix()  # about the file's up axis
Y_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # file y -> z


@pytest.mark.parametrize("variant", ["cgspeed", "facing_x", "z_up", "centimetres", "mixamo", "joint_map"])
def test_synthetic_cgspeed_pose_retargets_to_known_hinge_angles(tmp_path, model, variant):
    """Our rest proportions in a BVH: the hinge angles must be exactly the rotations written."""
    unit, up_axis, rename, joint_map = CMU_UNIT, "y", None, None
    to_file = BVH_TO_OURS.T
    if variant == "facing_x":
        to_file = YAW90 @ to_file
    elif variant == "z_up":
        to_file, up_axis = Y_TO_Z_UP @ to_file, "z"
    elif variant == "centimetres":
        unit = 0.01
    elif variant == "mixamo":
        rename = {n: (None if MIXAMO_NAMES.get(n, n) is None else "mixamorig:" + MIXAMO_NAMES.get(n, n))
                  for n in CGSPEED}
    elif variant == "joint_map":  # names no table knows, mapped by the caller
        rename = {n: f"bone{k}" for k, n in enumerate(CGSPEED)}
        joint_map = {body: rename[joint] for body, joint in JOINT_MAPS["cmu_cgspeed"].items()}
    joints = cgspeed_joints(unit, to_file, rename)
    names = [j[0] for j in joints]
    rots, root = pose_rotations(names, to_file, {k: v for k, v in (rename or {}).items() if v})
    path = write_bvh(tmp_path / "synthetic.bvh", joints, rots, root @ to_file.T / unit)

    result = retarget_bvh(parse_bvh(path), up_axis=up_axis, joint_map=joint_map, clip_to_range=False, model=model)
    motion = result.motion
    assert result.unit_scale == pytest.approx(unit)
    np.testing.assert_allclose(np.rad2deg(motion.dof_pos), np.rad2deg(expected_dofs()), atol=1e-4)
    np.testing.assert_allclose(motion.root_pos[:, :2], root[:, :2], atol=1e-6)
    np.testing.assert_allclose(motion.root_pos[:, 2], root[:, 2] + result.ground_offset, atol=1e-6)
    yaw = Rotation.from_quat(motion.root_quat, scalar_first=True).as_euler("ZYX", degrees=True)
    np.testing.assert_allclose(yaw, [[y, 0, 0] for y in ROOT_YAW_DEG], atol=1e-6)
    sole = foot_sole_heights(motion, model)
    assert -0.03 < sole.min() <= 1e-9  # grounded: the lowest foot reaches the floor


def test_non_t_pose_rest_is_aligned_by_bone_directions(tmp_path, model):
    """Arms-down, legs-apart rest and random joint rotations: our bones point where the BVH's do."""
    to_file = BVH_TO_OURS.T
    joints = cgspeed_joints(0.01, to_file, bend_rest=True)
    names = [j[0] for j in joints]
    rng = np.random.default_rng(0)
    t = 12
    rots = Rotation.from_rotvec(rng.normal(scale=0.35, size=(t * len(names), 3))).as_matrix()
    rots = rots.reshape(t, len(names), 3, 3)
    rots[0] = np.eye(3)  # the file's rest pose
    root = np.column_stack([np.linspace(0, 50, t), np.full(t, 95.0), np.zeros(t)])
    clip = parse_bvh(write_bvh(tmp_path / "bent.bvh", joints, rots, root, order="YXZ"))
    motion = retarget_bvh(clip, clip_to_range=False, model=model).motion

    body = compute_kinematics(motion, model).body_pos
    bvh = bvh_forward_kinematics(clip)[0] @ BVH_TO_OURS.T
    chains = [("L_Hip", "L_Knee", "LeftUpLeg", "LeftLeg"), ("L_Knee", "L_Ankle", "LeftLeg", "LeftFoot"),
              ("R_Hip", "R_Knee", "RightUpLeg", "RightLeg"), ("R_Knee", "R_Ankle", "RightLeg", "RightFoot"),
              ("L_Shoulder", "L_Elbow", "LeftArm", "LeftForeArm"),
              ("L_Elbow", "L_Wrist", "LeftForeArm", "LeftHand"),
              ("R_Shoulder", "R_Elbow", "RightArm", "RightForeArm"),
              ("R_Elbow", "R_Wrist", "RightForeArm", "RightHand"),
              ("Spine", "Chest", "Spine", "Spine1"), ("Neck", "Head", "Neck1", "Head")]
    pairs = [(BODY_NAMES.index(a), BODY_NAMES.index(b), names.index(c), names.index(d)) for a, b, c, d in chains]
    assert bone_angles_deg(body, bvh, pairs).max() < 0.01
    # In the file's rest, our arms hang down and our legs are 10 degrees apart.
    down = body[0, BODY_NAMES.index("L_Elbow")] - body[0, BODY_NAMES.index("L_Shoulder")]
    np.testing.assert_allclose(down / np.linalg.norm(down), [0, 0, -1], atol=1e-6)
    thigh = body[0, BODY_NAMES.index("R_Knee")] - body[0, BODY_NAMES.index("R_Hip")]
    np.testing.assert_allclose(thigh / np.linalg.norm(thigh), [0, -np.sin(np.radians(10)), -np.cos(np.radians(10))],
                               atol=1e-6)


def test_unit_detection_rejects_a_non_human_skeleton(tmp_path):
    joints = cgspeed_joints(1.0, BVH_TO_OURS.T)
    # legs 5 units long: 10 m in metres, 0.26 m in inches, 0.57 m in CMU units -> no person
    small = [(n, p, o * 5 / 0.835, e) for n, p, o, e in joints]
    rots, root = pose_rotations([j[0] for j in small], BVH_TO_OURS.T)
    path = write_bvh(tmp_path / "tiny.bvh", small, rots, root)
    with pytest.raises(ValueError, match="unit_scale"):
        load_bvh(path)
    motion = load_bvh(path, unit_scale=0.835 / 5)
    np.testing.assert_allclose(motion.dof_pos, expected_dofs(), atol=1e-4)  # 6-decimal offsets


def test_fitting_into_range_is_reported_keeps_angles_in_range_and_the_foot_in_place(tmp_path, model):
    joints = cgspeed_joints(CMU_UNIT, BVH_TO_OURS.T)
    names = [j[0] for j in joints]
    rots, root = pose_rotations(names, BVH_TO_OURS.T)
    hyperextended = Rotation.from_euler("y", -40, degrees=True).as_matrix()  # our knee axis
    rots[1, names.index("LeftLeg")] = BVH_TO_OURS.T @ hyperextended @ BVH_TO_OURS
    path = write_bvh(tmp_path / "hyper.bvh", joints, rots, root / CMU_UNIT)
    clip = parse_bvh(path)
    free = retarget_bvh(clip, clip_to_range=False, grounding=None, model=model)
    fitted = retarget_bvh(clip, grounding=None, model=model)
    imported = read_motion(path, grounding="constant", model=model)  # what `crisp import-motion` says
    assert imported.range_fit == (fitted.clipped_fraction, fitted.max_clip_deg)
    assert "of hinge values fitted into the joint ranges (a joint turned by up to 30°)" in imported.describe()
    ranges = np.deg2rad(np.concatenate([joint_range_deg(b) for b in BODY_NAMES[1:]]))
    outside = (free.motion.dof_pos < ranges[:, 0]) | (free.motion.dof_pos > ranges[:, 1])
    assert outside.any()
    changed = np.abs(fitted.motion.dof_pos - free.motion.dof_pos) > 1e-9
    assert fitted.clipped_fraction == pytest.approx(changed.mean())
    assert fitted.max_clip_deg == pytest.approx(30.0, abs=0.5)  # knee hyperextended -40 vs -10
    assert np.all(fitted.motion.dof_pos >= ranges[:, 0] - 1e-12)
    assert np.all(fitted.motion.dof_pos <= ranges[:, 1] + 1e-12)
    # Clipping the knee alone swings the shin. The fit turns the hip instead: the foot moves only by
    # the length the straighter leg has gained (its direction from the hip is kept).
    clipped = replace(free.motion, dof_pos=np.clip(free.motion.dof_pos, ranges[:, 0], ranges[:, 1]))
    hip, ankle = BODY_NAMES.index("L_Hip"), BODY_NAMES.index("L_Ankle")
    pos = {name: compute_kinematics(m, model).body_pos[1]  # from the pelvis: grounding shifts each its own way
           for name, m in (("free", free.motion), ("fitted", fitted.motion), ("clipped", clipped))}
    pos = {name: p - p[0] for name, p in pos.items()}
    leg = {name: np.linalg.norm(p[ankle] - p[hip]) for name, p in pos.items()}
    moved = {name: np.linalg.norm(pos[name][ankle] - pos["free"][ankle]) for name in ("fitted", "clipped")}
    assert moved["fitted"] == pytest.approx(leg["fitted"] - leg["free"], abs=1e-3)
    assert moved["clipped"] > 3 * moved["fitted"]


# --- grounding by planted feet ------------------------------------------------------------

STANCE_SPEED = 0.2  # m/s: a foot is planted while its ankle and toe move horizontally slower


def stance_frames(motion: Motion, model) -> np.ndarray:
    """(T,) frames in stance: at least one foot planted, i.e. both its ankle and toe joints move
    slower than STANCE_SPEED (velocity-threshold contact detection; a foot lifted straight up is
    horizontally still but not in stance)."""
    kin = compute_kinematics(motion, model)
    speed = {b: np.linalg.norm(kin.body_lin_vel[:, BODY_NAMES.index(b)], axis=1)
             for b in ("L_Ankle", "L_Toe", "R_Ankle", "R_Toe")}
    left = np.maximum(speed["L_Ankle"], speed["L_Toe"]) < STANCE_SPEED
    right = np.maximum(speed["R_Ankle"], speed["R_Toe"]) < STANCE_SPEED
    return left | right


def standing_motion(height: np.ndarray, fps: float = 30.0) -> Motion:
    """The rest pose standing still (feet planted) with the root at ``height`` per frame."""
    t = len(height)
    return Motion(fps=fps, root_pos=np.c_[np.zeros(t), np.zeros(t), height],
                  root_quat=np.tile([1.0, 0, 0, 0], (t, 1)), dof_pos=np.zeros((t, len(DOF_NAMES))))


def test_stance_grounding_removes_a_drifting_floor(model):
    """A still stance whose root rises and falls 3 cm (the capture's floor drifting): the drift is
    taken out, every frame's feet end on the floor and the root height becomes constant."""
    t = np.arange(120) / 30.0
    drift = 0.03 * (1 - np.cos(2 * np.pi * t / t[-1])) / 2
    motion = standing_motion(0.95 + drift)
    grounded = ground_stance(motion, model)
    np.testing.assert_allclose(foot_sole_heights(grounded, model), 0.0, atol=5e-4)
    assert np.ptp(grounded.root_pos[:, 2]) < 1e-3
    np.testing.assert_array_equal(grounded.root_pos[:, :2], motion.root_pos[:, :2])
    np.testing.assert_array_equal(grounded.dof_pos, motion.dof_pos)


def test_stance_grounding_keeps_walking_feet_on_the_floor(model):
    """The bundled flat walk (feet exactly on z = 0 whenever planted) with a slow 4 cm floor drift
    added: the correction recovers the floor to within a few millimetres in every frame."""
    clip = Motion.load(Path(__file__).parents[1] / "assets" / "clips" / "flat_walk" / "motion.npz")
    t = np.arange(clip.num_frames) / clip.fps
    drift = 0.04 * np.sin(2 * np.pi * t / t[-1])
    drifted = replace(clip, root_pos=clip.root_pos + np.c_[0 * t, 0 * t, drift])
    truth = foot_sole_heights(clip, model)
    assert np.abs(truth).max() < 1e-9 and stance_frames(clip, model).mean() > 0.85
    assert np.ptp(foot_sole_heights(drifted, model)) > 0.07  # the drift is there before
    np.testing.assert_allclose(foot_sole_heights(ground_stance(drifted, model), model), 0.0, atol=5e-3)


def test_stance_grounding_stays_within_its_shift_limit(model):
    """A drift larger than ``max_shift`` allows is followed only within it: the root height moves
    at most 2 * max_shift over the motion, and sits midway between floating and sinking."""
    t = np.arange(90) / 30.0
    drift = 0.2 * t / t[-1]  # 20 cm over the motion
    motion = standing_motion(0.95 + drift)
    for limit in (0.05, 0.02):
        floor = stance_floor(motion, model, StanceGrounding(max_shift=limit))
        assert np.ptp(floor) <= 2 * limit + 1e-12
        sole = foot_sole_heights(ground_stance(motion, model, StanceGrounding(max_shift=limit)), model)
        assert sole.min() == pytest.approx(-sole.max(), abs=2e-3)  # balanced: as much under as over
    with pytest.raises(ValueError, match="max_shift"):
        StanceGrounding(max_shift=0.0)


def test_a_short_dip_of_the_planted_feet_does_not_sink_them(model):
    """Feet that dip 1.5 cm for three frames (capture noise): the smooth floor correction passes
    under the dip instead of averaging through it, so no planted foot ends below the floor, and
    none floats by more than the dip."""
    height = np.full(90, 0.95)
    height[44:47] -= 0.015
    sole = foot_sole_heights(ground_stance(standing_motion(height), model), model)
    assert sole.min() >= -1e-9
    assert sole.max() <= 0.015 + 1e-9


def write_standing_bvh(path: Path) -> Path:
    """Our rest proportions standing still for 3 s at 30 fps, as motion capture often gives feet:
    the left sole rolled 15° about the foot's length, and both toes flipping between 40° curled
    into the floor and 40° up every half second."""
    to_file = BVH_TO_OURS.T
    joints = cgspeed_joints(CMU_UNIT, to_file)
    names = [j[0] for j in joints]
    t = 90

    def in_file(axis: str, degrees: float | np.ndarray) -> np.ndarray:
        """Rotations about our ``axis`` in the file's axes."""
        return to_file @ Rotation.from_euler(axis, degrees, degrees=True).as_matrix() @ to_file.T

    rots = np.broadcast_to(np.eye(3), (t, len(names), 3, 3)).copy()
    rots[:, names.index("LeftFoot")] = in_file("x", 15.0)
    curl = 40.0 * np.sign(np.sin(2 * np.pi * (np.arange(t) + 0.5) / 30))  # + is toes down in our axes
    for toe in ("LeftToeBase", "RightToeBase"):
        rots[:, names.index(toe)] = in_file("y", curl[:, None])
    root = np.tile(default_rest_joints(1.70)[0], (t, 1))
    return write_bvh(path, joints, rots, root @ to_file.T / CMU_UNIT)


def foot_geom_bottoms(motion: Motion, model) -> np.ndarray:
    """(T, G) lowest corner height of each foot box of the model."""
    data = mujoco.MjData(model)
    feet = {model.body(b).id for b in ("L_Ankle", "L_Toe", "R_Ankle", "R_Toe")}
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] in feet]
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    out = np.empty((motion.num_frames, len(geoms)))
    for k, qpos in enumerate(motion.qpos()):
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        for i, g in enumerate(geoms):
            points = data.geom_xpos[g] + (corners * model.geom_size[g]) @ data.geom_xmat[g].reshape(3, 3).T
            out[k, i] = points[:, 2].min()
    return out


def test_standing_feet_are_put_flat_on_the_floor(tmp_path, model):
    """A still stance with a rolled sole and curled, flipping toes: every foot box of the model
    rests on the floor in every frame, so the lowest joint is where the model's own standing feet
    put it (the toe joint of the rest pose, feet on z = 0), and the toes hold still."""
    motion = retarget_bvh(parse_bvh(write_standing_bvh(tmp_path / "stand.bvh")), model=model).motion
    bottoms = foot_geom_bottoms(motion, model)
    assert bottoms.min() >= -1e-6 and bottoms.max() <= 1e-3
    standing = default_rest_joints(1.70)[:, 2].min()  # 2.2 cm: joints sit above the sole
    lowest = compute_kinematics(motion, model).body_pos[:, :, 2].min(axis=1)
    np.testing.assert_allclose(lowest, standing, atol=1e-3)
    toes = [DOF_NAMES.index(f"{s}_Toe_{a}") for s in "LR" for a in "xyz"]
    assert np.abs(motion.qvel()[:, 6:][:, toes]).max() < 0.1


def test_a_standing_reference_is_held_without_chatter(tmp_path, model):
    """The PD servos at the reference (zero action) hold the still stance from reference state
    inits with almost no power. Toes curled into the floor and flipping against it saturate
    their servo, where MuJoCo drops the implicit damping and the light toe chatters at hundreds
    of rad/s: the energy term then reaches -100 per step and more."""
    motion = retarget_bvh(parse_bvh(write_standing_bvh(tmp_path / "stand.bvh")), model=model).motion
    clip = write_clip(tmp_path / "clip", [floor_box()], motion, {"source": "test"})
    env = gym.make("CrispTrack-v0", clip=str(clip))
    energy = []
    for start in range(0, 80, 10):
        env.reset(seed=0, options={"start_frame": start})
        for _ in range(8):
            _, _, terminated, truncated, info = env.step(np.zeros(env.action_space.shape))
            energy.append(info["reward_energy"])
            assert not terminated
    env.close()
    assert min(energy) > -0.5


def test_without_planted_feet_grounding_is_one_offset(tmp_path, model):
    """A motion whose feet never stay still gets the constant grounding, like ``grounding=None``."""
    joints = cgspeed_joints(CMU_UNIT, BVH_TO_OURS.T)
    rots, root = pose_rotations([j[0] for j in joints], BVH_TO_OURS.T)
    clip = parse_bvh(write_bvh(tmp_path / "fast.bvh", joints, rots, root @ BVH_TO_OURS / CMU_UNIT))
    drifting, constant = retarget_bvh(clip, model=model), retarget_bvh(clip, model=model, grounding=None)
    assert not stance_frames(drifting.motion, model).any()
    np.testing.assert_allclose(drifting.ground_offset, constant.ground_offset, atol=1e-12)
    assert np.ptp(constant.ground_offset) < 1e-12


# --- the real CMU clips --------------------------------------------------------------------


def _cmu_path(name: str) -> Path:
    path = CMU_DIR / f"{name}.bvh"
    if not path.is_file():
        pytest.skip(f"CMU sample not available at {path}")
    return path


@pytest.fixture(scope="module")
def cmu(model):
    """131_01 retargeted, and without clipping into the joint ranges or low-passing the hands."""
    path = _cmu_path("131_01")
    clip = parse_bvh(path)
    return (path, clip, model, retarget_bvh(clip, model=model),
            retarget_bvh(clip, clip_to_range=False, model=model, low_pass_hz=None))


@pytest.fixture(scope="module", params=CMU_CLIPS)
def cmu_clip(request, model):
    """Each CMU sample, retargeted."""
    path = _cmu_path(request.param)
    clip = parse_bvh(path)
    return path, clip, retarget_bvh(clip, model=model)


def _raw_hip_trajectory(path: Path) -> np.ndarray:
    """Root channel values read straight from the file (its first three are X/Y/Z position)."""
    lines = path.read_text().splitlines()
    start = next(k for k, line in enumerate(lines) if line.startswith("Frame Time")) + 1
    return np.loadtxt(lines[start:], usecols=(0, 1, 2))


def test_cmu_clip_root_follows_the_hips(cmu_clip):
    """The root path is the file's hip path in metres, z up, within the grounding's ``max_shift``.
    The file's floor level is its own (and our legs are longer), so heights are compared up to one
    constant."""
    path, _, result = cmu_clip
    assert result.unit_scale == pytest.approx(CMU_UNIT)
    hips = _raw_hip_trajectory(path) * CMU_UNIT  # y-up, facing +z, left +x
    expected = hips[:, [2, 0, 1]]  # -> ours: x forward, y left, z up
    root = result.motion.root_pos
    vertical = root[:, 2] - expected[:, 2]
    np.testing.assert_allclose(vertical, result.ground_offset, atol=1e-9)
    level = (vertical.max() + vertical.min()) / 2  # the constant that fits best
    assert abs(level) < 0.2  # the capture's floor is near the file's y = 0
    assert np.linalg.norm(root - expected - [0.0, 0.0, level], axis=1).max() <= StanceGrounding().max_shift + 1e-9


def test_cmu_clip_feet_touch_the_floor_in_stance(cmu_clip, model):
    """In stance frames the lowest foot point never sinks into the floor, is within 1 cm of it in
    85 % of them, 2 cm in 95 % and 3 cm in all; the planted soles are level (no rolled foot standing on
    its edge: the file's own soles roll by 10-20°); and the height correction adds no jitter to
    the root."""
    path, clip, result = cmu_clip
    motion = result.motion
    sole = foot_sole_heights(motion, model)
    stance = stance_frames(motion, model)
    assert stance.mean() > 0.5  # start, walk or hop, stop: mostly on the ground
    assert sole[stance].min() >= -1e-6 and sole[stance].max() < 0.03
    assert np.mean(sole[stance] < 0.01) > 0.85 and np.mean(sole[stance] < 0.02) > 0.95
    assert sole.min() > -0.03 and np.mean(sole < -0.01) < 0.03
    kin = compute_kinematics(motion, model)
    for side, planted in zip("LR", planted_feet(motion, model).T):
        normal = Rotation.from_quat(kin.body_quat[planted, BODY_NAMES.index(f"{side}_Ankle")],
                                    scalar_first=True).apply([0.0, 1.0, 0.0])
        tilt = np.abs(np.rad2deg(np.arcsin(normal[:, 2])))  # the sole's left-right tilt
        assert np.percentile(tilt, 95) < 2.5  # brief stances within a few frames are smoothed over
    # Jitter: the correction is a low-passed curve, gentler than the hips' own vertical motion. It
    # follows whichever planted foot is lower and passes under short dips of the feet, and with our
    # legs CMU's left and right stance heights differ by up to 4 cm, so it moves at up to 0.8 of the
    # hips' peak acceleration (131_01: 0.79, where a foot stands still for a few frames in the
    # crouch); the root's own peak acceleration stays that of the hips.
    dt = 1.0 / motion.fps
    accel = lambda z: np.abs(np.diff(z, 2)).max() / dt**2  # noqa: E731
    hips_z = clip.root_positions[:, 1] * result.unit_scale
    assert accel(result.ground_offset) < 0.8 * accel(hips_z)
    assert accel(motion.root_pos[:, 2]) < 1.1 * accel(hips_z)


def test_cmu_clip_with_one_offset_floats(cmu):
    """Why the per-frame correction exists: 131_01's capture floor drifts (its planted feet sit
    some 10 cm higher in the final stand than in the crouch), so one constant offset leaves most
    stance frames more than 3 cm off the floor."""
    _, clip, model, _, _ = cmu
    constant = retarget_bvh(clip, model=model, grounding=None).motion
    sole = foot_sole_heights(constant, model)[stance_frames(constant, model)]
    assert np.mean(np.abs(sole) < 0.03) < 0.5


def test_cmu_clip_plays_continuously(cmu):
    path, clip, _, result, _ = cmu
    motion = result.motion
    assert motion.num_frames == clip.num_frames and motion.fps == pytest.approx(120.0, rel=1e-3)
    for array in (motion.root_pos, motion.root_quat, motion.dof_pos):
        assert np.all(np.isfinite(array))
    # no 2*pi (or pi) flips: the largest per-frame change at 120 Hz is a fast wrist twist (~53 deg)
    assert np.rad2deg(np.abs(np.diff(motion.dof_pos, axis=0))).max() < 90.0
    resampled = load_bvh(path, target_fps=30.0)
    assert resampled.fps == 30.0
    assert resampled.num_frames == int(np.floor(motion.duration * 30.0 + 1e-9)) + 1


def test_cmu_clip_planted_feet_both_stand_on_the_floor(cmu_clip, model):
    """Each frame is grounded on its lower foot; the other planted foot, on our leg proportions up
    to 5 cm above the floor in the file (over 2 cm in 1.6-12 % of the planted feet), comes down with
    ``plant``: over 2 cm in at most 1 % of them and at most half as often as with the legs as
    captured, none below the floor, the pelvis where it was."""
    path, clip, result = cmu_clip
    planted = retarget_bvh(clip, model=model, grounding=StanceGrounding(plant=True)).motion
    shares = []
    for motion in (planted, result.motion):
        height = side_sole_heights(motion, model)[planted_feet(motion, model)]
        assert height.min() > -1e-3
        shares.append(np.mean(height > 0.02))
    assert shares[0] <= 0.01 and shares[0] <= shares[1] / 2
    np.testing.assert_allclose(planted.root_pos, result.motion.root_pos)


def test_cmu_clip_bone_directions_match(cmu):
    _, clip, model, clipped, free = cmu
    names = clip.skeleton.names
    bvh = bvh_forward_kinematics(clip)[0] @ free.to_ours.T
    legs = [("L_Hip", "L_Knee"), ("L_Knee", "L_Ankle"), ("R_Hip", "R_Knee"), ("R_Knee", "R_Ankle")]
    arms = [("L_Shoulder", "L_Elbow"), ("L_Elbow", "L_Wrist"), ("R_Shoulder", "R_Elbow"), ("R_Elbow", "R_Wrist")]

    def errors(result, chains):
        body = compute_kinematics(result.motion, model).body_pos
        pairs = [(BODY_NAMES.index(a), BODY_NAMES.index(b), names.index(result.joints[a]),
                  names.index(result.joints[b])) for a, b in chains]
        return bone_angles_deg(body, bvh, pairs)

    # The retarget itself reproduces every leg and arm bone direction.
    assert errors(free, legs + arms).max() < 0.01
    # Within the humanoid's joint ranges the legs stay close (kicks near the hip's gimbal lock clip).
    leg_err = errors(clipped, legs)
    assert leg_err.mean() < 2.0 and np.percentile(leg_err, 95) < 5.0


def test_cmu_hand_flicker_is_filtered(cmu_clip, model):
    """Captured wrists flicker (thousands of °/s between frames): the import low-passes the
    forearms and hands, so the peak wrist speed falls to under half of the raw retarget's."""
    _, clip, result = cmu_clip
    raw = retarget_bvh(clip, model=model, low_pass_hz=None)
    wrists = [DOF_NAMES.index(f"{side}_Wrist_{axis}") for side in "LR" for axis in "xyz"]

    def peak_speed(motion):
        return (np.abs(np.diff(motion.dof_pos[:, wrists], axis=0)) * motion.fps).max()

    assert peak_speed(result.motion) < 0.5 * peak_speed(raw.motion)
    legs = [i for i, name in enumerate(DOF_NAMES) if name.split("_")[1] in ("Hip", "Knee", "Ankle")]
    np.testing.assert_allclose(result.motion.dof_pos[:, legs], raw.motion.dof_pos[:, legs], atol=1e-9)
