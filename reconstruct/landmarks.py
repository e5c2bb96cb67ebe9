"""MediaPipe's 33 body landmarks (metric, world frame, z up) → a humanoid motion.

Each body's world orientation is built from landmark directions, our bone lengths are kept
(the landmarks' own limb lengths wander by 3-11 % from frame to frame; only their directions are
used), and the shared retargeting tail (:func:`crisp_gym.retarget.motion_from_rotations`) turns
them into hinge angles, lays planted feet flat and grounds them.

A body whose orientation two landmark directions fix (pelvis: the hip line and the trunk; chest:
the shoulder line and the trunk; head: the ear line and the nose; foot: heel-to-toe and the
shin) is built from both. A limb segment has one direction; its twist is taken as the smallest
turn from its parent (so an elbow or a knee bends about the axis across both of its segments),
except the thigh, whose twist follows the knee's bending plane when the knee is bent and the
foot's heading when it is straight. The spine's three bodies share the turn from pelvis to chest,
the neck half the turn from chest to head.

Seated (hips flexed past 40-70°), two things change. The pelvis takes its heading from the
thighs, not the hip line: the two hip landmarks then lie along the view and their depths are
unsure. And the thighs only flex in the pelvis's sagittal plane: the humanoid's x-y-z hip hinges
lock at 90° of flexion, and a thigh passing the horizontal with any splay or twist would swing its
x and z hinges by up to 180° (or be clipped to their range, which bends it somewhere else).
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES, build_humanoid, default_rest_joints
from crisp_gym.motion import StanceGrounding
from crisp_gym.reconstruct.person import landmark
from crisp_gym.retarget import Retargeted, motion_from_rotations

_STRAIGHT_KNEE_DEG = (15.0, 35.0)  # knee bend over which the thigh's twist moves from the foot to the knee
_NOSE_FROM_EARS = np.array([1.0, 0.0, -0.3])  # rest direction from the ears' midpoint to the nose
_SEATED_FLEXION_DEG = (40.0, 70.0)  # hip flexion over which the pelvis's heading moves from the hips to the thighs


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _frame(primary: np.ndarray, secondary: np.ndarray, primary_rest, secondary_rest) -> np.ndarray:
    """(T, 3, 3) rotations taking ``primary_rest`` onto ``primary`` and ``secondary_rest`` into the
    plane of ``primary`` and ``secondary`` (on its side)."""

    def basis(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        a = _unit(a)
        b = b - np.sum(a * b, axis=-1, keepdims=True) * a
        # A secondary along the primary fixes nothing (a straight knee's bending axis): any
        # perpendicular does; callers give such frames no weight.
        degenerate = np.linalg.norm(b, axis=-1) < 1e-9
        other = np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        b = np.where(degenerate[..., None], np.cross(a, other), b)
        b = _unit(b)
        return np.stack([a, b, np.cross(a, b)], axis=-1)

    rest = basis(np.asarray(primary_rest, float)[None], np.asarray(secondary_rest, float)[None])
    return basis(primary, secondary) @ np.swapaxes(rest, -1, -2)


def _smallest_turn(parent: np.ndarray, rest_direction, direction: np.ndarray) -> np.ndarray:
    """(T, 3, 3): ``parent`` turned by the smallest rotation taking its rest bone onto ``direction``."""
    start = _unit(parent @ np.asarray(rest_direction, float))
    end = _unit(direction)
    axis = np.cross(start, end)
    angle = np.arctan2(np.linalg.norm(axis, axis=-1), np.sum(start * end, axis=-1))
    turn = Rotation.from_rotvec(_unit(axis) * angle[:, None]).as_matrix()
    return turn @ parent


def _between(a: np.ndarray, b: np.ndarray, share: float | np.ndarray) -> np.ndarray:
    """(T, 3, 3): ``share`` (a number or (T,)) of the way from rotation ``a`` to ``b``, frame by frame."""
    rel = Rotation.from_matrix(np.swapaxes(a, -1, -2) @ b).as_rotvec()
    return a @ Rotation.from_rotvec(np.reshape(share, (-1, 1)) * rel).as_matrix()


def hips_and_trunk(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) midpoint of the hips and (T, 3) trunk vector from it to the shoulders' midpoint."""
    mid_hip = 0.5 * (points[:, landmark("left_hip")] + points[:, landmark("right_hip")])
    mid_shoulder = 0.5 * (points[:, landmark("left_shoulder")] + points[:, landmark("right_shoulder")])
    return mid_hip, mid_shoulder - mid_hip


def body_rotations(points: np.ndarray) -> np.ndarray:
    """(T, 24, 3, 3) world orientations of the humanoid's bodies from (T, 33, 3) landmarks (z up)."""
    p = {name: points[:, landmark(name)] for name in ("left_hip", "right_hip", "left_shoulder", "right_shoulder",
                                                      "left_ear", "right_ear", "nose")}
    _, trunk = hips_and_trunk(points)
    rest = default_rest_joints(1.0)
    at_rest = lambda *bodies: np.mean([rest[BODY_NAMES.index(b)] for b in bodies], axis=0)  # noqa: E731
    trunk_rest = at_rest("L_Shoulder", "R_Shoulder") - at_rest("L_Hip", "R_Hip")  # leans back 2° at rest

    def rest_bone(body: str, child: str) -> np.ndarray:
        return rest[BODY_NAMES.index(child)] - rest[BODY_NAMES.index(body)]

    out = np.empty((len(points), len(BODY_NAMES), 3, 3))
    put = lambda body, rot: out.__setitem__((slice(None), BODY_NAMES.index(body)), rot)  # noqa: E731
    get = lambda body: out[:, BODY_NAMES.index(body)]  # noqa: E731
    y, z = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    # The hip line sets the pelvis's heading standing, the thighs seated (on the bundled real
    # video the seated hip line is 15° off the thighs).
    thighs = sum(points[:, landmark(f"{s}_knee")] - points[:, landmark(f"{s}_hip")] for s in ("left", "right"))
    by_hips = _frame(p["left_hip"] - p["right_hip"], trunk, y, trunk_rest)
    by_thighs = _frame(trunk, thighs, trunk_rest, [1.0, 0.0, 0.0])
    flexion = np.rad2deg(np.arccos(np.clip(np.sum(_unit(-trunk) * _unit(thighs), axis=-1), -1.0, 1.0)))
    seated = np.clip((flexion - _SEATED_FLEXION_DEG[0]) / np.ptp(_SEATED_FLEXION_DEG), 0.0, 1.0)
    put("Pelvis", _between(by_hips, by_thighs, seated))
    chest = _frame(p["left_shoulder"] - p["right_shoulder"], trunk, y, trunk_rest)
    for body, part in (("Torso", 1 / 3), ("Spine", 2 / 3)):
        put(body, _between(get("Pelvis"), chest, part))
    put("Chest", chest)
    mid_ear = 0.5 * (p["left_ear"] + p["right_ear"])
    head = _frame(p["left_ear"] - p["right_ear"], p["nose"] - mid_ear, y, _NOSE_FROM_EARS)
    put("Neck", _between(chest, head, 0.5))
    put("Head", head)

    for side, name in (("L", "left"), ("R", "right")):
        lm = lambda part: points[:, landmark(f"{name}_{part}")]  # noqa: E731
        put(f"{side}_Thorax", chest)
        upper = _smallest_turn(chest, rest_bone(f"{side}_Shoulder", f"{side}_Elbow"), lm("elbow") - lm("shoulder"))
        put(f"{side}_Shoulder", upper)
        fore = _smallest_turn(upper, rest_bone(f"{side}_Elbow", f"{side}_Wrist"), lm("wrist") - lm("elbow"))
        put(f"{side}_Elbow", fore)
        hand = 0.5 * (lm("index") + lm("pinky"))
        put(f"{side}_Wrist", _smallest_turn(fore, rest_bone(f"{side}_Wrist", f"{side}_Hand"), hand - lm("wrist")))
        put(f"{side}_Hand", get(f"{side}_Wrist"))

        thigh_dir, shin_dir = lm("knee") - lm("hip"), lm("ankle") - lm("knee")
        foot_dir = lm("foot_index") - lm("heel")
        # Straight knee: the thigh faces where the foot points; bent: it bends about the knee's axis.
        by_foot = _frame(thigh_dir, foot_dir, -z, [1.0, 0.0, 0.0])
        by_knee = _frame(thigh_dir, np.cross(thigh_dir, shin_dir), -z, y)
        bend = np.rad2deg(np.arccos(np.clip(np.sum(_unit(thigh_dir) * _unit(shin_dir), axis=-1), -1, 1)))
        share = np.clip((bend - _STRAIGHT_KNEE_DEG[0]) / np.ptp(_STRAIGHT_KNEE_DEG), 0.0, 1.0)
        thigh = _between(by_foot, by_knee, share)
        # Seated, the thigh only flexes in the pelvis's sagittal plane (see the module docstring).
        in_pelvis = np.einsum("tji,tj->ti", get("Pelvis"), thigh_dir)
        flex = np.arctan2(-in_pelvis[:, 0], -in_pelvis[:, 2])
        sagittal = get("Pelvis") @ Rotation.from_rotvec(flex[:, None] * y).as_matrix()
        thigh = _between(thigh, sagittal, seated)
        put(f"{side}_Hip", thigh)
        shin = _smallest_turn(thigh, rest_bone(f"{side}_Knee", f"{side}_Ankle"), shin_dir)
        put(f"{side}_Knee", shin)
        put(f"{side}_Ankle", _frame(foot_dir, lm("knee") - lm("ankle"), [1.0, 0.0, 0.0], z))
        put(f"{side}_Toe", get(f"{side}_Ankle"))
    return out


def fill_gaps(points: np.ndarray) -> np.ndarray:
    """Landmarks with frames where nobody was found (NaN) linearly interpolated from their neighbours."""
    found = np.isfinite(points).all(axis=(1, 2))
    if not found.any():
        raise ValueError("no frame has a person in it")
    frames = np.arange(len(points))
    flat = points.reshape(len(points), -1)
    filled = np.stack([np.interp(frames, frames[found], flat[found, k]) for k in range(flat.shape[1])], axis=1)
    return filled.reshape(points.shape)


def leg_lengths(model: mujoco.MjModel) -> tuple[float, float]:
    """The humanoid's thigh (hip to knee) and shin (knee to ankle) lengths in metres."""
    knee, ankle = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name) for name in ("L_Knee", "L_Ankle"))
    return float(np.linalg.norm(model.body_pos[knee])), float(np.linalg.norm(model.body_pos[ankle]))


def with_leg_lengths(points: np.ndarray, thigh: float, shin: float) -> np.ndarray:
    """Landmarks whose legs have the given bone lengths: knee, ankle and foot moved along the
    landmarks' own bone directions from the hip down (the foot keeps its shape)."""
    out = points.copy()
    for side in ("left", "right"):
        hip, knee, ankle = (landmark(f"{side}_{j}") for j in ("hip", "knee", "ankle"))
        foot = [landmark(f"{side}_{j}") for j in ("heel", "foot_index")]
        out[:, knee] = out[:, hip] + thigh * _unit(points[:, knee] - points[:, hip])
        out[:, ankle] = out[:, knee] + shin * _unit(points[:, ankle] - points[:, knee])
        out[:, foot] = points[:, foot] + (out[:, ankle] - points[:, ankle])[:, None]
    return out


def landmarks_to_motion(points: np.ndarray, fps: float, *, model: mujoco.MjModel | None = None,
                        smoothing_seconds: float = 0.05,
                        grounding: StanceGrounding | None = StanceGrounding(), shift: bool = True) -> Retargeted:
    """The humanoid motion following (T, 33, 3) metric landmarks in a z-up world (NaN: not found).

    Landmarks are interpolated over gaps and smoothed over time (Gaussian, ``smoothing_seconds``);
    the pelvis is placed above the hips' midpoint as on our skeleton; the feet are laid flat and
    (unless ``shift=False``) grounded as in :func:`~crisp_gym.retarget.motion_from_rotations`.
    """
    points = fill_gaps(np.asarray(points, dtype=float))
    if smoothing_seconds > 0:
        points = gaussian_filter1d(points, smoothing_seconds * fps, axis=0, mode="nearest")
    rotations = body_rotations(points)
    model = model if model is not None else build_humanoid()
    hips = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name) for name in ("L_Hip", "R_Hip")]
    pelvis_above_hips = -model.body_pos[hips].mean(axis=0)  # the hips' offsets in the pelvis frame
    root = hips_and_trunk(points)[0] + rotations[:, 0] @ pelvis_above_hips
    return motion_from_rotations(rotations, root, fps, model=model, grounding=grounding, low_pass_hz=None,
                                 shift=shift)
