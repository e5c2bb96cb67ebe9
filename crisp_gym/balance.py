"""Can a body balance on its feet while it follows a motion? The centre of pressure it needs.

A reference's accelerations fix the external force and moment the ground must supply
(inverse dynamics of the humanoid with its root free). The ground can only push, and only
through the feet that touch it, so that wrench has to act at a point inside the feet's support
polygon: the centre of pressure (the zero-moment point of legged robotics). Where the motion
asks for one outside the polygon, no controller can follow it without falling or stepping
away; a tracking policy either learns to deviate or fails there. This is why synthetic
references are planned so that it stays inside, and it says how followable an imported clip is.

All positions are in metres, in the world frame of the motion; frames are the motion's.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from crisp_gym.humanoid import BODY_NAMES, FEET, HumanoidConfig, build_humanoid
from crisp_gym.motion import Motion

GRAVITY = 9.81


def distance_outside_hull(points_xy: np.ndarray, p: np.ndarray) -> float:
    """How far ``p`` lies outside the convex hull of ``points_xy`` (negative inside: minus the
    distance to the nearest edge); ``inf`` when the points span no area."""
    if len(points_xy) < 3:
        return float("inf")
    try:
        hull = ConvexHull(points_xy)
    except QhullError:
        return float("inf")
    return float(np.max(hull.equations[:, :2] @ p + hull.equations[:, 2]))


@dataclass(frozen=True)
class Balance:
    """The centre of pressure a motion needs, per frame (:func:`motion_balance`).

    Attributes:
        cop: (T, 2) xy where the ground's wrench must act, on the plane of the lowest sole
            in contact (NaN where no foot is).
        vertical_force: (T,) the ground's vertical force over body weight (1 standing still;
            below 0 the motion falls faster than gravity).
        outside: (T,) distance of ``cop`` outside the support polygon of the soles in contact
            (negative inside); NaN on frames that are not judged: no foot in contact, or
            another body (a seated pelvis, a hand) also bearing weight.
    """

    cop: np.ndarray
    vertical_force: np.ndarray
    outside: np.ndarray

    def share_outside(self, margin: float) -> float:
        """Share of the judged frames whose centre of pressure is more than ``margin`` m outside."""
        judged = self.outside[np.isfinite(self.outside)]
        return float((judged > margin).mean()) if len(judged) else 0.0


def motion_balance(motion: Motion, stature: float = 1.70) -> Balance:
    """The centre of pressure ``motion`` needs on the humanoid of ``stature`` (see the module
    docstring). ``motion.contacts`` says which feet touch the ground; without contacts every
    frame counts both feet as planted.

    Velocities and accelerations are central differences of the motion (its first and last
    frames repeat their neighbours'). Stepping between levels (stairs) puts the soles at
    different heights; the centre of pressure is then taken on the lower one's plane.
    """
    model = build_humanoid(HumanoidConfig(height=stature))
    data = mujoco.MjData(model)
    motion = motion.in_humanoid_order()
    qpos, qvel = motion.qpos(), motion.qvel()
    qacc = np.gradient(qvel, 1.0 / motion.fps, axis=0)
    feet = [BODY_NAMES.index(b) for b in FEET]
    contacts = motion.contacts
    if contacts is None:
        contacts = np.zeros((motion.num_frames, len(BODY_NAMES)), dtype=bool)
        contacts[:, feet] = True
    others = [i for i in range(len(BODY_NAMES)) if i not in feet]
    soles = {i: [g for g in range(model.ngeom) if model.geom_bodyid[g] == model.body(BODY_NAMES[i]).id
                 and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX] for i in feet}
    root = model.body(BODY_NAMES[0]).id
    weight = float(model.body_subtreemass[root]) * GRAVITY
    corners = np.array([[x, y, -1.0] for x in (-1.0, 1.0) for y in (-1.0, 1.0)])

    t = motion.num_frames
    cop, outside, vertical = np.full((t, 2), np.nan), np.full(t, np.nan), np.zeros(t)
    for k in range(t):
        data.qpos[:], data.qvel[:], data.qacc[:] = qpos[k], qvel[k], qacc[k]
        mujoco.mj_inverse(model, data)
        force = data.qfrc_inverse[:3]  # world frame (free joint's linear dofs)
        moment = data.xmat[root].reshape(3, 3) @ data.qfrc_inverse[3:6]  # about the root, world frame
        vertical[k] = force[2] / weight
        touching = [i for i in feet if contacts[k, i]]
        if not touching or force[2] <= 0:
            continue
        points = np.concatenate([
            data.geom_xpos[g] + (data.geom_xmat[g].reshape(3, 3) @ (corners * model.geom_size[g]).T).T
            for i in touching for g in soles[i]])
        ground = points[:, 2].min()
        # The wrench (force, moment about the root) acts at p on z = ground where its horizontal
        # moment vanishes: moment + (root - p) x force has zero x and y components.
        arm_z = data.xpos[root, 2] - ground
        arm_x = (moment[1] + arm_z * force[0]) / force[2]
        arm_y = (arm_z * force[1] - moment[0]) / force[2]
        cop[k] = data.xpos[root, :2] - (arm_x, arm_y)
        if not contacts[k, others].any():
            outside[k] = distance_outside_hull(points[:, :2], cop[k])
    return Balance(cop=cop, vertical_force=vertical, outside=outside)
