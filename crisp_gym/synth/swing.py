"""Swing-foot arcs: minimum-jerk profiles, the heel-off, and the smallest lift that keeps the foot
clear of every box."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from crisp_gym.metrics import box_signed_distance
from crisp_gym.scene import Box
from crisp_gym.synth.gait import FootMove, GaitParams, WalkPath
from crisp_gym.synth.skeleton import SIDE, Skeleton, rot_z


def min_jerk(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10 - 15 * u + 6 * u**2)


def min_jerk_between(u: np.ndarray, a: float, b: float) -> np.ndarray:
    return min_jerk((u - a) / (b - a))


def _swing_profile(move: FootMove, u: np.ndarray, lift: float) -> tuple[np.ndarray, np.ndarray]:
    """Arc length and sole height of a swing at phases ``u`` in [0, 1].

    Stepping up, the foot rises before it travels; stepping down, it travels before it drops;
    on the level both go together. ``lift`` is the extra height of the arc at mid-swing.
    """
    dz = move.z1 - move.z0
    if dz > 0.02:
        h, v = min_jerk_between(u, 0.2, 1.0), min_jerk_between(u, 0.0, 0.7)
    elif dz < -0.02:
        h, v = min_jerk_between(u, 0.0, 0.8), min_jerk_between(u, 0.3, 1.0)
    else:
        h, v = min_jerk_between(u, 0.0, 1.0), min_jerk_between(u, 0.0, 1.0)
    return move.s0 + (move.s1 - move.s0) * h, move.z0 + dz * v + lift * np.sin(np.pi * u) ** 2


def flat_ankle(path: WalkPath, s: np.ndarray, z: np.ndarray, side: int, gait: GaitParams,
                skel: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) ankle joint and (n,) yaw of a flat foot of ``side`` at arc ``s`` on a surface at ``z``."""
    s, z = np.asarray(s, dtype=float), np.asarray(z, dtype=float)
    xy = path.frame(s, np.full_like(s, SIDE[side] * gait.step_width / 2))
    return np.concatenate([xy, (z + skel.ankle_height)[:, None]], axis=1), path.heading(s) + SIDE[side] * gait.toe_out


def pitch_matrix(pitch: np.ndarray) -> np.ndarray:
    return Rotation.from_euler("y", np.asarray(pitch, dtype=float)[:, None]).as_matrix()


def heel_off(ankle: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, skel: Skeleton) -> np.ndarray:
    """Ankle of a foot raised by ``pitch`` (heel up) about the toe joint of its flat pose."""
    yaw_m = rot_z(yaw)
    pivot = ankle + yaw_m @ skel.toe_joint
    return pivot - np.einsum("nij,nj->ni", yaw_m @ pitch_matrix(pitch), np.broadcast_to(skel.toe_joint, ankle.shape))


def swing_pose(move: FootMove, u: np.ndarray, lift: float, side: int, path: WalkPath, gait: GaitParams,
                skel: Skeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ankle (n, 3), yaw, pitch and arc position of a swinging foot at phases ``u``.

    The heel-off pitch and the ankle offset it caused fade out over the first half of the swing.
    """
    s, z = _swing_profile(move, u, lift)
    ankle, yaw = flat_ankle(path, s, z, side, gait, skel)
    start, yaw0 = flat_ankle(path, [move.s0], [move.z0], side, gait, skel)
    raised = heel_off(start, yaw0, np.array([move.heel]), skel)
    fade = 1.0 - min_jerk_between(u, 0.0, 0.5)
    return ankle + (raised - start) * fade[:, None], yaw, move.heel * fade, s


def _foot_world(ankle: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, skel: Skeleton) -> np.ndarray:
    """(n, P, 3) world points of the foot: the hind foot pitched, the toe segment kept flat."""
    pts, toe = skel.foot_points()
    yaw_m = rot_z(yaw)
    foot = yaw_m @ pitch_matrix(pitch)
    hind = ankle[:, None] + np.einsum("nij,pj->npi", foot, pts)
    toe_origin = ankle + foot @ skel.toe_joint
    front = toe_origin[:, None] + np.einsum("nij,pj->npi", yaw_m, pts - skel.toe_joint)
    return np.where(toe[None, :, None], front, hind)


def swing_lift(move: FootMove, side: int, path: WalkPath, boxes: list[Box], skel: Skeleton, gait: GaitParams,
                clearance: float = 0.025) -> float:
    """Smallest arc height (in 1 cm steps from 4 cm) that keeps the swinging foot ``clearance``
    away from every box in mid-swing and out of them everywhere."""
    u = np.linspace(0.0, 1.0, 41)
    need = clearance * np.sin(np.pi * u) ** 2
    for lift in np.arange(0.04, 0.40, 0.01):
        ankle, yaw, pitch, _ = swing_pose(move, u, lift, side, path, gait, skel)
        world = _foot_world(ankle, yaw, pitch, skel)
        depth = -box_signed_distance(world.reshape(-1, 3), boxes).reshape(len(u), -1).min(axis=1)
        if np.all(depth + need <= 1e-6):
            return float(lift)
    raise RuntimeError(f"no swing arc clears the scene for the step {move}")
