"""From the sampled plan to joint angles: two-link leg IK (the stance foot flat and still), the
other hinges from the trunk and arm channels, a pelvis height the legs can reach, and checks on the
real model that lower the pelvis or raise a swing arc where needed."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.ndimage import gaussian_filter1d, maximum_filter1d
from scipy.optimize import lsq_linear
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES
from crisp_gym.metrics import scene_model
from crisp_gym.motion import Motion, compute_kinematics
from crisp_gym.scene import Box
from crisp_gym.synth.gait import GaitParams, MotionPlan, WalkPath
from crisp_gym.synth.skeleton import LEFT, RIGHT, SIDE, STANCE_BODIES, Skeleton, rot_z
from crisp_gym.synth.swing import flat_ankle, heel_off, min_jerk, min_jerk_between, pitch_matrix, swing_lift, swing_pose


def _leg_ik(hip: np.ndarray, ankle: np.ndarray, forward: np.ndarray, skel: Skeleton,
            reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Two-link IK: (T, 3, 3) thigh world rotations and (T,) knee flexion (rad, positive bends).

    The leg plane contains ``forward`` (the knee points that way); the thigh and shank hang
    along -z in the rest pose and the knee hinge is the thigh's y axis.
    """
    l1, l2 = skel.thigh, skel.shank
    d = ankle - hip
    dist = np.clip(np.linalg.norm(d, axis=1), abs(l1 - l2) + 1e-6, reach)
    interior = np.arccos(np.clip((l1**2 + l2**2 - dist**2) / (2 * l1 * l2), -1.0, 1.0))
    knee = np.pi - interior
    local = np.stack([-l2 * np.sin(knee), np.zeros_like(knee), -l1 - l2 * np.cos(knee)], axis=1)

    def frame(axis: np.ndarray, hint: np.ndarray) -> np.ndarray:
        e1 = axis / np.linalg.norm(axis, axis=1, keepdims=True)
        e2 = hint - np.sum(hint * e1, axis=1, keepdims=True) * e1
        e2 /= np.linalg.norm(e2, axis=1, keepdims=True)
        return np.stack([e1, e2, np.cross(e1, e2)], axis=2)

    world = frame(d, forward) @ np.swapaxes(frame(local, np.tile([1.0, 0.0, 0.0], (len(d), 1))), 1, 2)
    return world, knee


def _hinge_angles(local: np.ndarray) -> np.ndarray:
    """(T, J, 3) x-y-z hinge angles of (T, J, 3, 3) leg rotations, on the branch with the smaller
    x (ab/adduction, inversion) angle.

    A hip flexed past 90 degrees is on the second Euler branch (x + pi, pi - y, z + pi); choosing by
    the smaller x instead of by closeness to the previous frame stays correct through the
    near-singular frames of sitting down, where the frame-to-frame choice can lock onto the
    wrong branch.
    """
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    first = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_euler("XYZ").reshape(local.shape[:-2] + (3,))
    second = wrap(first + np.array([np.pi, 0.0, np.pi]))
    second[..., 1] = wrap(np.pi - first[..., 1])
    angles = np.where((np.abs(second[..., 0]) < np.abs(first[..., 0]))[..., None], second, first)
    return np.unwrap(angles, axis=0)


def _root_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    return Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()


def _dof(name: str) -> int:
    return DOF_NAMES.index(name)


@dataclass
class PoseFrames:
    """Per-frame targets that the IK turns into a motion."""

    pelvis_xy: np.ndarray  # (T, 2)
    pelvis_z: np.ndarray  # (T,)
    yaw: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray
    spine: np.ndarray  # trunk flexion above the pelvis (rad, forward positive)
    arms: np.ndarray  # extra shoulder flexion (rad)
    ankle: np.ndarray  # (T, 2, 3) ankle targets
    foot_yaw: np.ndarray  # (T, 2)
    foot_pitch: np.ndarray  # (T, 2) heel-off pitch (rad, heel up positive)
    foot_s: np.ndarray  # (T, 2) arc positions of the ankles (for the arm swing)
    pelvis_s: np.ndarray  # (T,)
    stance: np.ndarray  # (T, 2) bool
    phase: np.ndarray  # (T, 2) swing phase in [0, 1] (0 in stance)


def _hips(frames: PoseFrames, skel: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    rot = _root_rotation(frames.yaw, frames.pitch, frames.roll)
    pelvis = np.concatenate([frames.pelvis_xy, frames.pelvis_z[:, None]], axis=1)
    return rot, pelvis[:, None, :] + np.einsum("tij,lj->tli", rot, skel.hip)


def _limit_pelvis_height(frames: PoseFrames, skel: Skeleton, reach: float, fps: float) -> None:
    """Lower the pelvis where a leg could not reach its foot, keeping the height smooth."""
    rot, hips = _hips(frames, skel)
    horizontal = np.linalg.norm(hips[..., :2] - frames.ankle[..., :2], axis=2)
    drop = hips[..., 2] - frames.pelvis_z[:, None]
    limit = frames.ankle[..., 2] + np.sqrt(np.maximum(reach**2 - horizontal**2, 0.0)) - drop
    # A swinging leg shortens itself by flexing; it only has to reach near lift-off and landing.
    free = ~frames.stance & (frames.phase > 0.1) & (frames.phase < 0.85)
    limit = np.where(free, np.inf, limit).min(axis=1)
    frames.pelvis_z = _smooth_below(frames.pelvis_z, limit, fps)


_HEIGHT_ACCEL_WEIGHT = 0.03  # m of height error that weigh as much as 1 m/s² of vertical acceleration
_HEIGHT_KEPT_WEIGHT = 100.0  # weight of the planned height, relative, where the legs are far from straight


def _smooth_below(z: np.ndarray, limit: np.ndarray, fps: float) -> np.ndarray:
    """The height closest to ``z`` with small vertical accelerations that stays under ``limit``
    (bounded least squares). Where the legs are far from straight (a seated pelvis) the planned
    height weighs :data:`_HEIGHT_KEPT_WEIGHT` times more, so that it stays on its seat.

    Clipping to the limit alone dipped the pelvis by up to 10 cm within a few frames at each
    double support: vertical accelerations near ±g that no leg force produces.
    """
    n = len(z)
    if n < 3:
        return np.minimum(z, limit)
    accel = np.zeros((n - 2, n))
    rows = np.arange(n - 2)
    accel[rows, rows], accel[rows, rows + 1], accel[rows, rows + 2] = 1.0, -2.0, 1.0
    slack = np.clip((limit - z - 0.1) / 0.1, 0.0, 1.0)  # 0 up to 10 cm under the reach, 1 from 20 cm
    weight = 1.0 + (_HEIGHT_KEPT_WEIGHT - 1.0) * slack
    matrix = np.vstack([np.diag(weight), _HEIGHT_ACCEL_WEIGHT * fps**2 * accel])
    return lsq_linear(matrix, np.concatenate([weight * z, np.zeros(n - 2)]), bounds=(-np.inf, limit),
                      method="bvls").x


def solve_joints(frames: PoseFrames, skel: Skeleton, gait: GaitParams, fps: float, reach: float) -> Motion:
    """Joint angles for the per-frame targets: legs by IK, the rest from the trunk/arm channels."""
    t = len(frames.pelvis_z)
    rot, hips = _hips(frames, skel)
    foot_rot = np.stack([rot_z(frames.foot_yaw[:, i]) @ pitch_matrix(frames.foot_pitch[:, i])
                         for i in range(2)], axis=1)
    heading = np.stack([np.cos(frames.yaw), np.sin(frames.yaw), np.zeros(t)], axis=1)
    dof = np.zeros((t, len(DOF_NAMES)))
    local = np.empty((t, 4, 3, 3))
    knees, shanks = [], []
    for leg in range(2):
        toward = foot_rot[:, leg, :, 0] + heading
        thigh, knee = _leg_ik(hips[:, leg], frames.ankle[:, leg], toward, skel, reach)
        shanks.append(thigh @ Rotation.from_euler("y", knee[:, None]).as_matrix())
        local[:, 2 * leg] = np.swapaxes(rot, 1, 2) @ thigh
        local[:, 2 * leg + 1] = np.swapaxes(shanks[leg], 1, 2) @ foot_rot[:, leg]
        knees.append(knee)
    angles = _hinge_angles(local)
    # A swinging foot tucked behind the body points its toes down instead of staying flat
    # (the leg IK does not depend on the foot's orientation, so only the ankle changes).
    for leg in range(2):
        extra = np.maximum(_SWING_DORSIFLEXION - angles[:, 2 * leg + 1, 1], 0.0)
        # Smoothly, and flat again before landing so the toes cannot catch the next surface.
        u = frames.phase[:, leg]
        fade = np.where(frames.stance[:, leg], 0.0, min_jerk_between(u, 0.0, 0.2) * (1.0 - min_jerk_between(u, 0.45, 0.8)))
        extra = gaussian_filter1d(maximum_filter1d(extra * fade, 5), 1.0) * fade
        local[:, 2 * leg + 1] = local[:, 2 * leg + 1] @ pitch_matrix(extra)
    angles = _hinge_angles(local)
    for leg, side in enumerate("LR"):
        for axis_index, axis in enumerate("xyz"):
            dof[:, _dof(f"{side}_Hip_{axis}")] = angles[:, 2 * leg, axis_index]
            dof[:, _dof(f"{side}_Ankle_{axis}")] = angles[:, 2 * leg + 1, axis_index]
        dof[:, _dof(f"{side}_Knee_y")] = knees[leg]
        dof[:, _dof(f"{side}_Toe_y")] = -frames.foot_pitch[:, leg]  # the toe stays flat

    # Trunk: lean spread over three joints, counter-rotation against the pelvis yaw oscillation,
    # head kept level; arms hang 75 degrees down and swing against the legs.
    path_yaw = frames.yaw - _pelvis_twist(frames)
    for name in ("Torso", "Spine", "Chest"):
        dof[:, _dof(f"{name}_y")] = frames.spine / 3
        dof[:, _dof(f"{name}_z")] = -(frames.yaw - path_yaw) / 3
        dof[:, _dof(f"{name}_x")] = -frames.roll / 3
    dof[:, _dof("Neck_y")] = -(frames.pitch + frames.spine) * 0.5
    dof[:, _dof("Head_y")] = -(frames.pitch + frames.spine) * 0.5
    lead = frames.foot_s - frames.pelvis_s[:, None]
    for leg, side in enumerate("LR"):
        sign = SIDE[leg]
        swing = -gait.arm_swing * lead[:, leg] + frames.arms  # forward positive
        dof[:, _dof(f"{side}_Shoulder_x")] = -sign * np.deg2rad(75.0)
        dof[:, _dof(f"{side}_Shoulder_z")] = -sign * swing
        dof[:, _dof(f"{side}_Elbow_z")] = -sign * np.deg2rad(8.0)

    pelvis = np.concatenate([frames.pelvis_xy, frames.pelvis_z[:, None]], axis=1)
    quat = Rotation.from_matrix(rot).as_quat(scalar_first=True)
    quat *= np.where(quat[:, :1] < 0, -1.0, 1.0)
    return Motion(fps=fps, root_pos=pelvis, root_quat=quat, dof_pos=dof)


def _pelvis_twist(frames: PoseFrames) -> np.ndarray:
    """Pelvis yaw oscillation of gait: the swing-side hip comes forward with its foot."""
    return -0.12 * (frames.foot_s[:, LEFT] - frames.foot_s[:, RIGHT])


def sample_plan(plan: MotionPlan, path: WalkPath, boxes: list[Box], skel: Skeleton, gait: GaitParams,
              fps: float) -> PoseFrames:
    """Sample the plan at ``fps``: pelvis channels, stance holds, heel-offs and swing arcs."""
    t = np.arange(int(round(plan.end * fps)) + 1) / fps
    n = len(t)
    ankle, foot_yaw = np.empty((n, 2, 3)), np.empty((n, 2))
    foot_pitch, foot_s = np.zeros((n, 2)), np.empty((n, 2))
    stance = np.ones((n, 2), dtype=bool)
    phase = np.zeros((n, 2))
    for foot in range(2):
        moves = plan.moves[foot]
        s_hold = np.full(n, moves[0].s0 if moves else plan.feet[foot][0])
        z_hold = np.full(n, moves[0].z0 if moves else plan.feet[foot][1])
        for move in moves:
            after = t >= move.land
            s_hold[after], z_hold[after] = move.s1, move.z1
        ankle[:, foot], foot_yaw[:, foot] = flat_ankle(path, s_hold, z_hold, foot, gait, skel)
        foot_s[:, foot] = s_hold
        for move in moves:
            rolling = (t >= move.lift - move.roll) & (t <= move.lift)
            if rolling.any() and move.roll > 0:
                pitch = move.heel * min_jerk((t[rolling] - move.lift + move.roll) / move.roll)
                ankle[rolling, foot] = heel_off(ankle[rolling, foot], foot_yaw[rolling, foot], pitch, skel)
                foot_pitch[rolling, foot] = pitch
            inside = (t > move.lift) & (t < move.land)
            if not inside.any():
                continue
            lift = swing_lift(move, foot, path, boxes, skel, gait)
            u = (t[inside] - move.lift) / (move.land - move.lift)
            (ankle[inside, foot], foot_yaw[inside, foot], foot_pitch[inside, foot],
             foot_s[inside, foot]) = swing_pose(move, u, lift, foot, path, gait, skel)
            stance[inside, foot] = False
            phase[inside, foot] = u
    pelvis_s, lat = plan.channel("s", t), plan.channel("lat", t)
    frames = PoseFrames(
        pelvis_xy=path.frame(pelvis_s, lat), pelvis_z=plan.channel("z", t), yaw=path.heading(pelvis_s),
        pitch=plan.channel("pitch", t), roll=0.8 * lat, spine=plan.channel("spine", t),
        arms=plan.channel("arms", t), ankle=ankle, foot_yaw=foot_yaw, foot_pitch=foot_pitch,
        foot_s=foot_s, pelvis_s=pelvis_s, stance=stance, phase=phase)
    frames.yaw = frames.yaw + _pelvis_twist(frames)
    return frames


_SWING_DORSIFLEXION = np.deg2rad(-40.0)  # most a swinging ankle flexes before the toes drop
_REACH = 0.995  # fraction of the full leg length a stance leg may extend to (knee ~11 deg)


def plan_to_motion(frames: PoseFrames, skel: Skeleton, gait: GaitParams, fps: float, model: mujoco.MjModel,
               boxes: list[Box]) -> Motion:
    """IK, then checks on the real model: where a stance ankle misses its target the pelvis is
    lowered, and where a swinging foot (its toes dropped by the IK) touches the scene its arc
    is raised; both are redone until neither happens."""
    _limit_pelvis_height(frames, skel, _REACH * skel.leg, fps)
    scene = scene_model(boxes, skel.stature)
    feet = [[scene.body(b).id for b in bodies] for bodies in STANCE_BODIES]
    data = mujoco.MjData(scene)
    for _ in range(8):
        motion = solve_joints(frames, skel, gait, fps, skel.leg * 0.9999)
        ankles = compute_kinematics(motion, model).body_pos[:, [BODY_NAMES.index("L_Ankle"),
                                                             BODY_NAMES.index("R_Ankle")]]
        miss = np.where(frames.stance, np.linalg.norm(ankles - frames.ankle, axis=2), 0.0).max(axis=1)
        depth = _swing_penetration(motion, frames, scene, data, feet)
        if miss.max() < 1e-4 and depth.max() < 1e-4:
            return motion
        frames.pelvis_z = frames.pelvis_z - gaussian_filter1d(maximum_filter1d(miss, 9), 2.0) * 1.5
        raise_by = gaussian_filter1d(maximum_filter1d(depth + 0.005 * (depth > 0), 9, axis=0), 2.0, axis=0)
        frames.ankle[..., 2] += raise_by * np.sin(np.pi * frames.phase) * ~frames.stance
    raise RuntimeError(f"the legs cannot reach the planned footholds (miss {miss.max():.4f} m) or the "
                       f"swinging feet cannot clear the scene (depth {depth.max():.4f} m)")


def _swing_penetration(motion: Motion, frames: PoseFrames, scene: mujoco.MjModel, data: mujoco.MjData,
                       feet: list[list[int]]) -> np.ndarray:
    """(T, 2) deepest penetration of each swinging foot into the scene."""
    depth = np.zeros((motion.num_frames, 2))
    qpos = motion.qpos()
    for k in np.flatnonzero(~frames.stance.all(axis=1)):
        data.qpos[:] = qpos[k]
        mujoco.mj_kinematics(scene, data)
        mujoco.mj_collision(scene, data)
        for c in data.contact[:data.ncon]:
            bodies = {scene.geom_bodyid[c.geom1], scene.geom_bodyid[c.geom2]}
            for leg in range(2):
                if not frames.stance[k, leg] and bodies & set(feet[leg]):
                    depth[k, leg] = max(depth[k, leg], -c.dist)
    return depth
