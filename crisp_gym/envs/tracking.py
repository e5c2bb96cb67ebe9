"""The tracking task as pure functions over arrays with a leading batch dimension N.

Both :class:`~crisp_gym.envs.track.CrispTrackEnv` (one ``MjData``) and
:class:`~crisp_gym.envs.track_vector.CrispTrackVectorEnv` (``mujoco.batch.Batch``) read the
same MuJoCo fields into a :class:`SimState` and call these functions, so they agree exactly.

Observation features follow the paper (after MaskedMimic): everything is expressed in the
root's *heading* frame (the pelvis yaw), rotations as the rotated x and z axes.

=====================  ==========================================================  ==========
key                    content                                                     shape
=====================  ==========================================================  ==========
``proprio``            root height (1); body positions relative to the root (24×3); (361,)
                       body rotations (24×6); body linear (24×3) and angular
                       (24×3) velocities
``targets``            for each of the next K reference frames and each body:      (K, 432)
                       rotation of reference relative to sim (6), reference
                       rotation (6), reference − sim position (3), reference
                       position relative to the sim root (3)
``points``             N scene surface points nearest the pelvis, relative to it   (N, 3)
                       (scene-aware only)
=====================  ==========================================================  ==========
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from pathlib import Path

import mujoco
import numpy as np
import trimesh
from scipy.spatial import cKDTree

from crisp_gym.envs import quat
from crisp_gym.envs.config import TrackConfig
from crisp_gym.humanoid import BODY_NAMES, HumanoidConfig, build_humanoid_spec, servo_damping
from crisp_gym.mjcf_scene import attach_scene, surface_points
from crisp_gym.motion import Motion, compute_kinematics
from crisp_gym.render import style_scene
from crisp_gym.scene import Box, add_boxes, sample_surface_points

NUM_BODIES = len(BODY_NAMES)
PROPRIO_DIM = 1 + NUM_BODIES * (3 + 6 + 3 + 3)
TARGET_DIM = NUM_BODIES * (6 + 6 + 3 + 3)
REWARD_TERMS = ("pos", "rot", "vel", "ang_vel", "height", "energy")
"""The paper's six reward terms."""


def reward_term_names(cfg: TrackConfig) -> tuple[str, ...]:
    """The terms the env's reward sums for ``cfg``: the paper's six, and ``root_pos`` when weighted."""
    return (*REWARD_TERMS, "root_pos") if cfg.w_root_pos > 0 else REWARD_TERMS


def reward_info(terms: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The reward terms as flat ``info`` entries, ``reward_pos`` ... ``reward_energy`` (as gymnasium's
    MuJoCo envs report theirs; flat keys also read into TorchRL's fixed info specs)."""
    return {f"reward_{name}": value for name, value in terms.items()}


def terms_from_info(info: dict) -> dict[str, np.ndarray]:
    """The reward terms back from an env's ``info`` (see :func:`reward_info`)."""
    return {key.removeprefix("reward_"): value for key, value in info.items() if key.startswith("reward_")}


def build_track_spec(boxes: list[Box], timestep: float,
                     scene_xmls: Sequence[tuple[Path, np.ndarray]] = ()) -> mujoco.MjSpec:
    """The humanoid composed with the scene's boxes, plus a camera that follows the pelvis.

    ``scene_xmls``, for clips whose scene is not boxes, adds each file's geometry (meshes,
    heightfields) shifted by its (3,) offset.
    """
    spec = build_humanoid_spec(HumanoidConfig(timestep=timestep))
    add_boxes(spec, boxes)
    for i, (scene_xml, offset) in enumerate(scene_xmls):
        attach_scene(spec, scene_xml, prefix="scene/" if len(scene_xmls) == 1 else f"scene{i}/", offset=offset)
    spec.worldbody.add_light(name="key", pos=(0, 0, 5), dir=(0.3, 0.2, -1), castshadow=True,
                             type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, diffuse=(0.6, 0.6, 0.6))
    # 4.6 m back, looking 14° down at the pelvis: the whole body and a few metres of scene
    spec.body("Pelvis").add_camera(name="follow", mode=mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM,
                                   pos=(0.0, -4.5, 1.1), xyaxes=(1, 0, 0, 0, 0.25, 1))
    style_scene(spec)
    return spec


def build_track_model(boxes: list[Box], timestep: float,
                      scene_xmls: Sequence[tuple[Path, np.ndarray]] = ()) -> mujoco.MjModel:
    """Compile :func:`build_track_spec`: the model ``CrispTrack-v0`` simulates."""
    return build_track_spec(boxes, timestep, scene_xmls).compile()


@dataclass(frozen=True)
class Reference:
    """The reference motion at the control rate, with everything the task reads per frame."""

    qpos: np.ndarray  # (T, 76)
    qvel: np.ndarray  # (T, 75)
    body_pos: np.ndarray  # (T, 24, 3)
    body_quat: np.ndarray  # (T, 24, 4)
    body_lin_vel: np.ndarray  # (T, 24, 3)
    body_ang_vel: np.ndarray  # (T, 24, 3)
    # (T, 24, 6) each body's rotated x and z axes (quat.tangent_normal of body_quat): the targets
    # read them every step, so they are computed once
    body_axes: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "body_axes", quat.tangent_normal(self.body_quat))

    @property
    def num_frames(self) -> int:
        return self.qpos.shape[0]

    @property
    def dof_pos(self) -> np.ndarray:
        return self.qpos[:, 7:]

    @classmethod
    def from_motion(cls, motion: Motion, model: mujoco.MjModel, control_hz: float) -> Reference:
        motion = motion.in_humanoid_order().resample(control_hz)
        if motion.num_frames < 2:
            raise ValueError("the motion is shorter than one control step")
        k = compute_kinematics(motion, model)
        return cls(qpos=k.qpos, qvel=k.qvel, body_pos=k.body_pos, body_quat=k.body_quat,
                   body_lin_vel=k.body_lin_vel, body_ang_vel=k.body_ang_vel)

    def translated(self, offset: np.ndarray) -> Reference:
        """The same motion shifted by ``offset`` (3,) (velocities and rotations unchanged)."""
        offset = np.asarray(offset, dtype=float)
        qpos = self.qpos.copy()
        qpos[:, :3] += offset
        return replace(self, qpos=qpos, body_pos=self.body_pos + offset)

    @classmethod
    def concatenate(cls, references: Sequence[Reference]) -> Reference:
        """``references`` end to end (frame rows stacked)."""
        return cls(**{f.name: np.concatenate([getattr(r, f.name) for r in references]) for f in fields(cls) if f.init})


@dataclass(frozen=True)
class SimState:
    """What the task reads from the simulator, (N, ...) arrays."""

    qpos: np.ndarray
    qvel: np.ndarray
    body_pos: np.ndarray
    body_quat: np.ndarray
    body_lin_vel: np.ndarray
    body_ang_vel: np.ndarray
    servo_torque: np.ndarray

    @cached_property
    def body_rot_pair(self) -> np.ndarray:
        """(N, B, 6, 6) ``[[R, 0], [0, R]]`` of each body's rotation (:func:`quat.matrix_pair`):
        computed once for the proprioception's axes and the target features."""
        return quat.matrix_pair(self.body_quat)


# The x and z axes (columns 0 and 2 of R) in a flattened body_rot_pair: R[i, j] is entry 6 i + j.
_AXES_IN_PAIR = np.array([0, 6, 12, 2, 8, 14])


def sim_state(qpos, qvel, xpos, xquat, cvel, subtree_com, actuator_force, qfrc_damper, body_ids) -> SimState:
    """Assemble a :class:`SimState` from MuJoCo fields (each with a leading N).

    ``servo_torque`` (N, 69): see :func:`servo_torque`.

    ``cvel`` is the spatial velocity (angular, linear) at the root's subtree centre of mass,
    so a body origin moves with ``v + ω × (x_body − c)``.
    """
    pos = np.take(xpos, body_ids, axis=1)  # np.take: a copy, as fancy indexing, at half its cost
    vel = np.take(cvel, body_ids, axis=1)
    ang = vel[..., :3]  # a view of this private copy
    # the root's subtree centre of mass, repeated per body: subtracting equal shapes runs over
    # whole rows, where broadcasting a (N, 1, 3) runs an inner loop of 3 per body
    lin = quat.cross(ang, pos - np.take(subtree_com, np.repeat(body_ids[:1], len(body_ids)), axis=1))
    lin += vel[..., 3:]
    return SimState(qpos=qpos, qvel=qvel, body_pos=pos, body_quat=np.take(xquat, body_ids, axis=1),
                    body_lin_vel=lin, body_ang_vel=ang, servo_torque=servo_torque(actuator_force, qfrc_damper))


def servo_torque(actuator_force: np.ndarray, qfrc_damper: np.ndarray) -> np.ndarray:
    """(..., 69) each hinge servo's whole torque: its clamped PD force (``actuator_force``) plus its
    passive damping (``qfrc_damper`` past the free root's six dofs; only the hinges are damped,
    in actuator order)."""
    return actuator_force + qfrc_damper[..., 6:]


def _heading_inverse(root_quat: np.ndarray) -> np.ndarray:
    """(N, 1, 4) inverse heading rotation, to broadcast over bodies."""
    return quat.conjugate(quat.yaw_quat(root_quat))[:, None, :]


def proprioception(state: SimState) -> np.ndarray:
    """(N, 361) the paper's s_t in the heading frame."""
    # Every block but the root height is a list of 3-vectors turned into the heading frame:
    # gather them as rows and rotate them all with one matrix product per env.
    pos = state.body_pos
    n, nb = pos.shape[:2]
    rows = np.empty((n, 5 * nb, 3))  # body − root positions, x and z axes (per body), lin, ang
    np.subtract(pos, np.take(pos, np.zeros(nb, dtype=int), axis=1), out=rows[:, :nb])  # (see sim_state)
    axes = rows[:, nb:3 * nb].reshape(n, nb, 6)
    np.take(state.body_rot_pair.reshape(n, nb, 36), _AXES_IN_PAIR, axis=2, out=axes, mode="clip")
    rows[:, 3 * nb:4 * nb] = state.body_lin_vel
    rows[:, 4 * nb:] = state.body_ang_vel
    # the heading is the yaw of the root's x axis (quat.yaw's arguments, bit for bit)
    heading = quat.inverse_yaw_matrix(np.arctan2(axes[:, 0, 1], axes[:, 0, 0]))
    out = np.empty((n, 1 + 15 * nb))
    out[:, 0] = pos[:, 0, 2]
    np.matmul(rows, heading, out=out[:, 1:].reshape(n, 5 * nb, 3))  # a view of out after the height
    return out


def target_features(state: SimState, ref: Reference, frames: np.ndarray) -> np.ndarray:
    """(N, K, 432) the paper's f̂ for reference frames ``frames`` (N, K)."""
    # Per body and frame the 18 features are six 3-vectors: the reference x and z axes in the
    # sim body's frame (rel_rot), the same axes in the heading frame (ref_rot), and
    # reference − sim body and reference − sim root in the heading frame (diff_pos, rel_pos).
    # Each block is a matrix product written straight into its columns of the output.
    n, k = frames.shape
    sim_pos = state.body_pos
    nb = sim_pos.shape[1]
    rows = k * nb
    out = np.empty((n, k, nb, 18))
    sim_rot = state.body_rot_pair  # (N, B, 6, 6) blockdiag(R, R)
    heading = quat.inverse_yaw_matrix(np.arctan2(sim_rot[:, 0, 1, 0], sim_rot[:, 0, 0, 0]))  # root's yaw
    ref_axes = ref.body_axes[frames]  # (N, K, B, 6)
    # rel_rot: [x, z] @ blockdiag(R, R) = [Rᵀx, Rᵀz], one product per (env, body) over the K frames
    np.matmul(ref_axes.transpose(0, 2, 1, 3), sim_rot, out=out[..., :6].transpose(0, 2, 1, 3))
    # ref_rot: both axes into the heading frame, one product per env
    heading_pair = np.zeros((n, 6, 6))
    heading_pair[:, :3, :3] = heading_pair[:, 3:, 3:] = heading
    np.matmul(ref_axes.reshape(n, rows, 6), heading_pair, out=out[..., 6:12].reshape(n, rows, 6))
    # diff_pos and rel_pos: subtract over whole (B·3) rows, then one product per env
    ref_pos = ref.body_pos[frames].reshape(n, k, nb * 3)
    diff = ref_pos - sim_pos.reshape(n, 1, nb * 3)
    np.matmul(diff.reshape(n, rows, 3), heading, out=out[..., 12:15].reshape(n, rows, 3))
    ref_pos -= np.take(sim_pos, np.zeros(nb, dtype=int), axis=1).reshape(n, 1, nb * 3)
    np.matmul(ref_pos.reshape(n, rows, 3), heading, out=out[..., 15:18].reshape(n, rows, 3))
    return out.reshape(n, k, nb * 18)


def future_frames(frame: np.ndarray, num_future: int, last_frame: int | np.ndarray) -> np.ndarray:
    """(N, K) the next K frame indices after ``frame``, held at ``last_frame`` (a scalar or (N,))."""
    return np.minimum(frame[:, None] + np.arange(1, num_future + 1), np.reshape(last_frame, (-1, 1)))


def nearest_points(root_pos: np.ndarray, root_quat: np.ndarray, tree: cKDTree, count: int) -> np.ndarray:
    """(N, count, 3) the scene samples nearest the pelvis, in its heading frame, nearest first.

    ``root_pos`` (N, 3) and ``root_quat`` (N, 4) are the pelvis's; ``tree`` is a KD-tree over
    the scene samples (``cKDTree(points)``): with ~10⁴ samples and 64 envs a brute-force
    distance matrix made this query a third of a training step.
    """
    count_available = min(count, tree.n)
    _, idx = tree.query(root_pos, k=count_available)
    idx = np.asarray(idx).reshape(len(root_pos), count_available)
    chosen = tree.data[idx] - root_pos[:, None]
    if count_available < count:  # fewer samples than slots: repeat the farthest
        chosen = np.concatenate([chosen, np.repeat(chosen[:, -1:], count - count_available, axis=1)], axis=1)
    return quat.rotate(_heading_inverse(root_quat), chosen)


def reward_terms(state: SimState, ref: Reference, frame: np.ndarray, cfg: TrackConfig) -> dict[str, np.ndarray]:
    """The paper's six reward terms, each (N,) and already weighted, and ``root_pos`` when
    ``cfg.w_root_pos > 0``; the reward is their sum."""
    n, nb = state.body_pos.shape[:2]
    err = np.empty((5, n))  # pos, vel, ang_vel, rot, height
    # per-body Euclidean errors of position, linear and angular velocity, summed over bodies
    sq = np.empty((3, n, nb, 3))
    np.subtract(ref.body_pos[frame], state.body_pos, out=sq[0])
    np.subtract(ref.body_lin_vel[frame], state.body_lin_vel, out=sq[1])
    np.subtract(ref.body_ang_vel[frame], state.body_ang_vel, out=sq[2])
    sq *= sq
    dist = sq[..., 0] + sq[..., 1]  # summed over xyz as np.linalg.norm does
    dist += sq[..., 2]
    np.sqrt(dist, out=dist).sum(-1, out=err[:3])
    # rotation: the angle of ref ⊗ sim⁻¹, whose scalar part is the 4-D dot product, summed in
    # the Hamilton product's order (arccos near 1 magnifies any rounding difference)
    prod = ref.body_quat[frame] * state.body_quat
    cos_half = prod[..., 0] + prod[..., 1]
    cos_half += prod[..., 2]
    cos_half += prod[..., 3]
    quat.angle(cos_half[..., None]).sum(-1, out=err[3])
    np.abs(ref.body_pos[frame, 0, 2] - state.body_pos[:, 0, 2], out=err[4])
    err *= [[-cfg.a_pos], [-cfg.a_vel], [-cfg.a_ang_vel], [-cfg.a_rot], [-cfg.a_height]]
    terms = np.exp(err, out=err)
    terms *= [[cfg.w_pos], [cfg.w_vel], [cfg.w_ang_vel], [cfg.w_rot], [cfg.w_height]]
    power = np.minimum(np.abs(state.servo_torque * state.qvel[:, 6:]).sum(-1), cfg.max_power)
    out = {"pos": terms[0], "rot": terms[3], "vel": terms[1], "ang_vel": terms[2], "height": terms[4],
           "energy": -cfg.w_energy * power}
    if cfg.w_root_pos > 0:  # the pelvis alone (its distance from above), so a drifted body is still pulled back
        out["root_pos"] = cfg.w_root_pos * np.exp(-cfg.a_root_pos * dist[0, :, 0])
    return out


def farthest_body(state: SimState, ref: Reference, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) the largest distance (m) of any body from its reference, and (N,) which body that is
    (its index in :data:`~crisp_gym.humanoid.BODY_NAMES`): the one that ends an episode."""
    diff = ref.body_pos[frame] - state.body_pos
    diff *= diff
    dist = diff[..., 0] + diff[..., 1]  # squared, summed as np.linalg.norm does
    dist += diff[..., 2]
    body = dist.argmax(-1)
    return np.sqrt(dist[np.arange(len(body)), body]), body


def damping_lead(model: mujoco.MjModel) -> np.ndarray:
    """(nu,) ``kd / kp`` of each position actuator (s; ``kd`` inside the servo or as its passive
    damping): how far its servo lags a target moving at constant speed, since the servo damps
    the joint's velocity, not its error."""
    return servo_damping(model) / model.actuator_gainprm[:, 0]


def pd_targets(action: np.ndarray, ref: Reference, next_frame: np.ndarray, cfg: TrackConfig,
               ranges: np.ndarray, lead: np.ndarray | None = None) -> np.ndarray:
    """(N, 69) PD targets: residual on the next reference pose, or absolute within the ranges.

    With ``cfg.velocity_feedforward`` the residual targets also lead the reference by ``lead``
    (69,) seconds (:func:`damping_lead`) times its hinge velocities, at most
    ``cfg.max_feedforward_lead`` radians either way.
    """
    action = np.clip(action, -1.0, 1.0)
    if cfg.residual_actions:
        targets = ref.dof_pos[next_frame] + cfg.action_scale * action
        if cfg.velocity_feedforward:
            if lead is None:
                raise ValueError("velocity_feedforward needs the actuators' damping lead (damping_lead(model))")
            limit = cfg.max_feedforward_lead
            targets += np.clip(lead * ref.qvel[next_frame, 6:], -limit, limit)
        return targets
    mid, half = ranges.mean(axis=1), 0.5 * (ranges[:, 1] - ranges[:, 0])
    return mid + half * action


def scene_samples(boxes: list[Box], ref: Reference, cfg: TrackConfig) -> np.ndarray:
    """(P, 3) surface samples of the scene within ``point_radius`` of the pelvis path."""
    points, _ = sample_surface_points(_cropped(boxes, ref.body_pos[:, 0], cfg.point_radius), cfg.point_spacing)
    return _near_path(points, ref.body_pos[:, 0], cfg.point_radius)


def mesh_scene_samples(surface: trimesh.Trimesh, ref: Reference, cfg: TrackConfig) -> np.ndarray:
    """(P, 3) samples of a triangulated scene surface within ``point_radius`` of the pelvis path."""
    path = ref.body_pos[:, 0]
    lo, hi = path[:, :2].min(0) - cfg.point_radius, path[:, :2].max(0) + cfg.point_radius
    corners = surface.vertices[surface.faces][..., :2]  # (F, 3, 2): keep faces touching the path's box
    keep = np.all(corners.max(1) >= lo, axis=1) & np.all(corners.min(1) <= hi, axis=1)
    if not keep.any():
        return np.zeros((0, 3))
    return _near_path(surface_points(surface.submesh([np.flatnonzero(keep)], append=True), cfg.point_spacing),
                      path, cfg.point_radius)


def _near_path(points: np.ndarray, path: np.ndarray, radius: float) -> np.ndarray:
    """The ``points`` within ``radius`` (horizontally) of the pelvis ``path``."""
    step = max(1, len(path) // 200)
    d = np.min(np.linalg.norm(points[:, None, :2] - path[None, ::step, :2], axis=-1), axis=1)
    return points[d <= radius]


def _cropped(boxes: list[Box], path: np.ndarray, radius: float) -> list[Box]:
    """Axis-aligned boxes clipped to the path's neighbourhood (the floor is 40 m wide)."""
    lo, hi = path.min(0) - radius, path.max(0) + radius
    out = []
    for box in boxes:
        if not np.allclose(box.rotation, np.eye(3)):
            out.append(box)
            continue
        b_lo = np.maximum(box.center - box.half_size, [lo[0], lo[1], -np.inf])
        b_hi = np.minimum(box.center + box.half_size, [hi[0], hi[1], np.inf])
        if np.all(b_hi > b_lo):
            out.append(Box(center=(b_lo + b_hi) / 2, half_size=(b_hi - b_lo) / 2, source=box.source))
    return out

