"""The humanoid's geometry as the motion generator plans with it: leg segment lengths, hip and foot
offsets, and the left/right conventions."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES

LEFT, RIGHT = 0, 1  # index of the left and right foot
SIDE = np.array([1.0, -1.0])  # lateral sign of the left and right foot (left is +y)
STANCE_BODIES = (("L_Ankle", "L_Toe"), ("R_Ankle", "R_Toe"))


@dataclass(frozen=True)
class Skeleton:
    """Leg and foot geometry of the humanoid, read from its MuJoCo model (rest pose, metres).

    Attributes:
        hip: (2, 3) left/right hip joint offsets from the pelvis origin, pelvis frame.
        thigh, shank: hip→knee and knee→ankle lengths.
        ankle_height: ankle joint above the sole when the foot is flat.
        heel, toe: foot extent behind/ahead of the ankle joint; half_width: half its width.
        foot_top: top of the foot above the sole.
        toe_joint: (3,) toe joint relative to the ankle joint (the heel-off pivot).
        pelvis_height: pelvis origin above the soles in the rest pose.
        stature: the humanoid's height (m), to compose scene models of the same humanoid.
    """

    hip: np.ndarray
    thigh: float
    shank: float
    ankle_height: float
    heel: float
    toe: float
    half_width: float
    foot_top: float
    toe_joint: np.ndarray
    pelvis_height: float
    stature: float

    @property
    def leg(self) -> float:
        return self.thigh + self.shank

    @classmethod
    def from_model(cls, model: mujoco.MjModel, stature: float) -> Skeleton:
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        pos = {name: data.xpos[model.body(name).id].copy() for name in BODY_NAMES}
        foot_ids = {model.body("L_Ankle").id, model.body("L_Toe").id}
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for g in range(model.ngeom):
            if model.geom_bodyid[g] in foot_ids:
                lo = np.minimum(lo, data.geom_xpos[g] - model.geom_size[g])
                hi = np.maximum(hi, data.geom_xpos[g] + model.geom_size[g])
        ankle = pos["L_Ankle"]
        return cls(
            hip=np.stack([pos["L_Hip"] - pos["Pelvis"], pos["R_Hip"] - pos["Pelvis"]]),
            thigh=float(np.linalg.norm(pos["L_Knee"] - pos["L_Hip"])),
            shank=float(np.linalg.norm(pos["L_Ankle"] - pos["L_Knee"])),
            ankle_height=float(ankle[2] - lo[2]), heel=float(ankle[0] - lo[0]), toe=float(hi[0] - ankle[0]),
            half_width=float((hi[1] - lo[1]) / 2), foot_top=float(hi[2] - lo[2]),
            toe_joint=pos["L_Toe"] - ankle, pelvis_height=float(pos["Pelvis"][2] - lo[2]), stature=stature)

    def foot_points(self) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) points filling the foot box relative to the ankle joint, and (P,) which of
        them belong to the toe segment (ahead of the toe joint)."""
        xs = np.linspace(-self.heel, self.toe, 13)
        ys = np.linspace(-self.half_width, self.half_width, 4)
        zs = np.linspace(0.0, self.foot_top, 3) - self.ankle_height
        pts = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)
        return pts, pts[:, 0] > self.toe_joint[0]


def rot_z(a: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations about +z by the angles ``a`` (T,): a foot's or the pelvis's heading."""
    return Rotation.from_euler("z", np.asarray(a)[:, None]).as_matrix()
