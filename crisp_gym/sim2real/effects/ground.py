"""Effects of the ground: friction, contact softness, height, tilt, and a missing support box."""

from __future__ import annotations

import mujoco
import numpy as np

from crisp_gym.sim2real.effects.base import CannotApply, Effect, Param
from crisp_gym.sim2real.models import SUPPORT_SLOT, lowest_point
from crisp_gym.sim2real.replay import Trajectory


def ground_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Colliding geoms of the world body: the floor and any static support."""
    colliding = (model.geom_contype != 0) | (model.geom_conaffinity != 0)
    return np.flatnonzero((model.geom_bodyid == 0) & colliding)


def ground_top(model: mujoco.MjModel) -> float:
    """Height of the highest top face among the ground geoms (boxes, planes, others by
    their bounding sphere)."""
    tops = []
    for g in ground_geoms(model):
        z = float(model.geom_pos[g, 2])
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            mat = np.zeros(9)
            mujoco.mju_quat2Mat(mat, model.geom_quat[g])
            z += float(np.abs(mat.reshape(3, 3)[2]) @ model.geom_size[g])
        elif model.geom_type[g] != mujoco.mjtGeom.mjGEOM_PLANE:
            z += float(model.geom_rbound[g])
        tops.append(z)
    return max(tops)


class GroundEffect(Effect):
    touches_model, per_joint_allowed = True, False

    def applicable(self, tr: Trajectory) -> bool:
        return len(ground_geoms(tr.model)) > 0


class GroundFriction(GroundEffect):
    """The ground's sliding friction coefficient differs from the model's."""

    name = family = "ground_friction"

    def params(self, tr: Trajectory) -> list[Param]:
        g = ground_geoms(tr.model)
        return [Param("mu", float(tr.model.geom_friction[g[0], 0]), 0.02, 2.5, 0.01, "")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([m]) for m in (0.1, 0.4, 1.0)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        model.geom_friction[ground_geoms(model), 0] = x[0]


class ContactSoftness(GroundEffect):
    """The ground (or the feet's padding) is softer or stiffer: solref time constant."""

    name = family = "contact_softness"

    def params(self, tr: Trajectory) -> list[Param]:
        g = ground_geoms(tr.model)
        return [Param("timeconst", float(tr.model.geom_solref[g[0], 0]), 0.002, 0.3, 5e-4, "s")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([t]) for t in (0.01, 0.04, 0.1)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        model.geom_solref[ground_geoms(model), 0] = x[0]


class GroundHeight(GroundEffect):
    """The ground is higher or lower than modelled."""

    name = family = "ground_height"

    def params(self, tr: Trajectory) -> list[Param]:
        return [Param("offset", 0.0, -0.08, 0.08, 2e-4, "m")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([h]) for h in (-0.02, 0.0, 0.02)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        model.geom_pos[ground_geoms(model), 2] += x[0]


class GroundTilt(GroundEffect):
    """The ground is tilted about the world x and y axes (radians)."""

    name = family = "ground_tilt"

    def params(self, tr: Trajectory) -> list[Param]:
        return [Param("roll", 0.0, -0.3, 0.3, 1e-3, "rad"), Param("pitch", 0.0, -0.3, 0.3, 1e-3, "rad")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([r, p]) for r in (-0.05, 0.05) for p in (-0.05, 0.05)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        tilt = np.zeros(4)
        mujoco.mju_euler2Quat(tilt, np.array([x[0], x[1], 0.0]), "xyz")
        for g in ground_geoms(model):
            out = np.zeros(4)
            mujoco.mju_mulQuat(out, tilt, model.geom_quat[g])
            model.geom_quat[g] = out
            rotated = np.zeros(3)
            mujoco.mju_rotVecQuat(rotated, model.geom_pos[g], tilt)
            model.geom_pos[g] = rotated


class SupportBox(GroundEffect):
    """A support the scene lacks: a box standing on the ground, its top ``height`` above
    the ground, centred at (``x``, ``y``) in the world. It moves the model's parked
    placeholder box into place (see :func:`~crisp_gym.sim2real.models.add_support_slot`):
    a compiled model cannot gain a geom, so models without the placeholder skip it."""

    name = family = "support_box"
    refine = 3

    def applicable(self, tr: Trajectory) -> bool:
        return super().applicable(tr) and mujoco.mj_name2id(tr.model, mujoco.mjtObj.mjOBJ_GEOM, SUPPORT_SLOT) >= 0

    def params(self, tr: Trajectory) -> list[Param]:
        xy = support_points(tr)
        lo, hi = xy.min(axis=0) - 0.15, xy.max(axis=0) + 0.15
        # Coarse difference steps: contacts with the box's edges make the cost rugged at the mm scale.
        return [Param("height", 0.0, 0.0, 0.1, 5e-4, "m"), Param("x", float(xy[0, 0]), float(lo[0]), float(hi[0]), 5e-3, "m"),
                Param("y", float(xy[0, 1]), float(lo[1]), float(hi[1]), 5e-3, "m")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        # A grid: the box's edges meet the moving feet in many places (local minima).
        return [np.array([h, x + dx, y + dy]) for x, y in support_points(tr) for dx in np.linspace(-0.12, 0.12, 7)
                for dy in (-0.04, 0.0, 0.04) for h in (0.01, 0.025)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        if x[0] <= 0.0:
            return  # no box: the placeholder stays parked
        g = model.geom(SUPPORT_SLOT).id
        ref = ground_geoms(model)[0]
        model.body_pos[model.geom_bodyid[g]] = (x[1], x[2], ground_top(model) + x[0] - model.geom_size[g, 2])
        for field in ("geom_contype", "geom_conaffinity", "geom_condim", "geom_friction", "geom_solref", "geom_solimp"):
            getattr(model, field)[g] = getattr(model, field)[ref]
        # The broad phase filters by the per-body masks compiled from the geoms' masks.
        model.body_contype[model.geom_bodyid[g]] = model.geom_contype[g]
        model.body_conaffinity[model.geom_bodyid[g]] = model.geom_conaffinity[g]


SUPPORT_POSTURES = 16
"""Postures of a log (evenly spaced) searched for the geoms a missing support could hold."""


def _resting(tr: Trajectory, qpos: np.ndarray, moving: np.ndarray, top: float, data: mujoco.MjData) -> list:
    """xy of the ``moving`` geoms resting on something in posture ``qpos``: within 2 cm of its
    lowest geom and at most a support box's height (0.1 m) above the modelled ground ``top``."""
    data.qpos[tr.qadr] = qpos
    mujoco.mj_kinematics(tr.model, data)
    low = np.array([lowest_point(tr.model, data, g) for g in moving])
    return [data.geom_xpos[g, :2].copy() for g in moving[(low < low.min() + 0.02) & (low < top + 0.12)]]


def support_points(tr: Trajectory) -> np.ndarray:
    """(k, 2) world xy of the moving geoms that rest on something (the feet): where a missing
    support can act; the start points of its fit. Taken at the log's mean posture, else, when
    nothing rests there (a leg in swing half the time), over :data:`SUPPORT_POSTURES` postures
    of the log; a ground higher than modelled still holds them (the lowest geoms count)."""
    m = tr.model
    colliding = (m.geom_contype != 0) | (m.geom_conaffinity != 0)
    moving = np.flatnonzero(colliding & (m.geom_bodyid != 0))
    if not len(moving):
        raise CannotApply("no moving geom collides with anything: a missing support could not hold anything")
    data, top = mujoco.MjData(m), ground_top(m)
    found = _resting(tr, tr.log.qpos.mean(axis=0), moving, top, data)
    if not found:
        postures = tr.log.qpos[np.linspace(0, len(tr.log.qpos) - 1, SUPPORT_POSTURES).astype(int)]
        found = [xy for qpos in postures for xy in _resting(tr, qpos, moving, top, data)]
    pts: list[np.ndarray] = []
    for xy in found:
        if not any(np.linalg.norm(p - xy) < 0.02 for p in pts):
            pts.append(xy)
    if not pts:
        raise CannotApply("no moving geom comes within 12 cm of the modelled ground in the log: a missing "
                          "support could not hold anything")
    return np.array(pts)
