"""Where the humanoid touches a support: each body's contact patch (a few world points per frame)
and the body parts they belong to."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES, build_humanoid
from crisp_gym.motion import Motion, compute_kinematics

PARTS: dict[str, tuple[str, ...]] = {
    "foot": ("L_Ankle", "L_Toe", "R_Ankle", "R_Toe"),
    "seat": ("Pelvis", "L_Hip", "R_Hip"),
    "hand": ("L_Hand", "R_Hand"),
    "back": ("Torso", "Spine", "Chest"),
}
"""Body-part groups with their own contact cue and filter thresholds; other bodies are ``"other"``."""


PART_OF: dict[str, str] = {body: next((p for p, bodies in PARTS.items() if body in bodies), "other")
                           for body in BODY_NAMES}
"""Body name -> its part group."""


UP = np.array([0.0, 0.0, 1.0])
_SEAT_THIGH_SPAN = 0.5  # fraction of the thigh from the hip that bears the seated weight


@dataclass(frozen=True)
class BodyGeometry:
    """Where each body of a posed motion would touch a support, frame by frame (world frame).

    Attributes:
        fps: frame rate of the motion.
        patches: 24 arrays (one per body, :data:`BODY_NAMES` order) of shape (T, K, 3): the
            body's contact patch in every frame (see the module docstring).
        speed: (T, 24) speed of each patch's centroid (m/s), by central differences.
        body_pos: (T, 24, 3) body (joint) positions.
        forward: (T, 3) the pelvis's horizontal facing direction (unit).
        com: (T, 3) whole-body centre of mass.
        standing_pelvis: height of the pelvis above the soles in the humanoid's rest pose (m).
    """

    fps: float
    patches: tuple[np.ndarray, ...]
    speed: np.ndarray
    body_pos: np.ndarray
    forward: np.ndarray
    com: np.ndarray
    standing_pelvis: float

    @property
    def num_frames(self) -> int:
        return self.speed.shape[0]

    def centroid(self, body: int) -> np.ndarray:
        """(T, 3) centroid of one body's patch."""
        return self.patches[body].mean(axis=1)


def _body_geom(model: mujoco.MjModel, body: str) -> int:
    """The (first) collision geom of a humanoid body."""
    bid = model.body(body).id
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == bid]
    if not geoms:
        raise ValueError(f"humanoid body {body!r} has no geom to take a contact patch from")
    return geoms[0]


def _geom_poses(model: mujoco.MjModel, geom: int, pos: np.ndarray, rot: Rotation) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) world centre and (T, 3, 3) world axes of a geom from its body's poses."""
    local = Rotation.from_quat(model.geom_quat[geom], scalar_first=True)
    return pos + rot.apply(model.geom_pos[geom]), (rot * local).as_matrix()


def _box_sole(center: np.ndarray, axes: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(T, 5, 3) centre and corners of the lowest face of a box in every frame."""
    t = np.arange(len(center))
    vertical = np.argmax(np.abs(axes[:, 2, :]), axis=1)  # the box axis closest to z
    sign = -np.sign(axes[t, 2, vertical])
    face = center + (sign * half[vertical])[:, None] * axes[t, :, vertical]
    others = np.array([[a for a in range(3) if a != v] for v in range(3)])[vertical]
    u = axes[t, :, others[:, 0]] * half[others[:, 0]][:, None]
    v = axes[t, :, others[:, 1]] * half[others[:, 1]][:, None]
    corners = [face + su * u + sv * v for su in (-1, 1) for sv in (-1, 1)]
    return np.stack([face, *corners], axis=1)


def _capsule_line(center: np.ndarray, axes: np.ndarray, size: np.ndarray, joint: np.ndarray,
                  span: float, side: np.ndarray) -> np.ndarray:
    """(T, 3, 3) points on a capsule's surface facing ``side`` (T, 3), along its axis from the
    end at ``joint`` over the fraction ``span`` of its length."""
    radius, half_length = size[0], size[1]
    axis = axes[:, :, 2]
    # Orient the axis from the joint end to the free end.
    flip = np.einsum("ti,ti->t", joint - center, axis) > 0
    axis = np.where(flip[:, None], -axis, axis)
    start = center - half_length * axis
    offset = side - np.einsum("ti,ti->t", side, axis)[:, None] * axis
    norm = np.linalg.norm(offset, axis=1, keepdims=True)
    # Along the side direction itself the surface point is undefined; fall back to ``side``.
    offset = np.where(norm > 1e-6, offset / np.maximum(norm, 1e-12), side)
    fractions = np.array([0.0, 0.5, 1.0]) * span
    return np.stack([start + f * 2 * half_length * axis + radius * offset for f in fractions], axis=1)


def _standing_pelvis_height(model: mujoco.MjModel) -> float:
    """Pelvis origin above the lowest foot-box point in the rest pose."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    soles = [data.geom_xpos[g][2] - model.geom_size[g][2]
             for g in (_body_geom(model, b) for b in PARTS["foot"])]
    return float(data.xpos[model.body("Pelvis").id][2] - min(soles))


def body_geometry(motion: Motion, model: mujoco.MjModel | None = None) -> BodyGeometry:
    """Contact patches, their speeds and the centre of mass of ``motion`` posed on ``model``.

    ``model`` is the humanoid the motion was made for (default: :func:`build_humanoid`).
    """
    model = model or build_humanoid()
    motion = motion.in_humanoid_order()
    kin = compute_kinematics(motion, model)
    t = motion.num_frames
    rots = [Rotation.from_quat(kin.body_quat[:, i], scalar_first=True) for i in range(len(BODY_NAMES))]
    forward = rots[0].apply([1.0, 0.0, 0.0]) * [1.0, 1.0, 0.0]
    forward /= np.maximum(np.linalg.norm(forward, axis=1, keepdims=True), 1e-9)
    down = np.broadcast_to(-UP, (t, 3))

    patches: list[np.ndarray | None] = [None] * len(BODY_NAMES)
    for i, body in enumerate(BODY_NAMES):
        g = _body_geom(model, body)
        center, axes = _geom_poses(model, g, kin.body_pos[:, i], rots[i])
        size = model.geom_size[g]
        kind = model.geom_type[g]
        if kind == mujoco.mjtGeom.mjGEOM_BOX:
            patches[i] = _box_sole(center, axes, size)
        elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            patches[i] = (center - size[0] * UP)[:, None, :]
        elif body == "Pelvis":
            continue  # needs the thighs; below
        elif PART_OF[body] == "back":
            patches[i] = _capsule_line(center, axes, size, kin.body_pos[:, i], 1.0, -forward)
        else:
            span = _SEAT_THIGH_SPAN if PART_OF[body] == "seat" else 1.0
            patches[i] = _capsule_line(center, axes, size, kin.body_pos[:, i], span, down)
    pelvis = BODY_NAMES.index("Pelvis")
    g = _body_geom(model, "Pelvis")
    center, axes = _geom_poses(model, g, kin.body_pos[:, pelvis], rots[pelvis])
    half = model.geom_size[g][1] * axes[:, :, 2]
    axis_points = np.stack([center - half, center, center + half], axis=1)
    hips = [patches[BODY_NAMES.index(b)][:, 0, 2] for b in ("L_Hip", "R_Hip")]
    axis_points[:, :, 2] = np.mean(hips, axis=0)[:, None]
    patches[pelvis] = axis_points

    dt = 1.0 / motion.fps
    speed = np.stack([np.linalg.norm(np.gradient(p.mean(axis=1), dt, axis=0), axis=1) for p in patches], axis=1)
    mass = model.body_mass[[model.body(b).id for b in BODY_NAMES]]
    ipos = np.stack([rots[i].apply(model.body_ipos[model.body(b).id]) for i, b in enumerate(BODY_NAMES)], axis=1)
    com = np.einsum("b,tbi->ti", mass, kin.body_pos + ipos) / mass.sum()
    return BodyGeometry(fps=motion.fps, patches=tuple(patches), speed=speed, body_pos=kin.body_pos,
                        forward=forward, com=com, standing_pelvis=_standing_pelvis_height(model))
