"""Effects on the joints' and actuators' dynamics: Coulomb friction, viscous damping, armature, PD gain
scale, torque saturation."""

from __future__ import annotations

import mujoco
import numpy as np

from crisp_gym.sim2real.effects.base import Effect, Param, inertia_scale, speed_scale, torque_scale
from crisp_gym.sim2real.replay import Trajectory


class DofEffect(Effect):
    """Adds a parameter to a per-dof model field (friction, damping, armature)."""

    touches_model = True
    field = ""
    unit = ""

    def scale(self, tr: Trajectory) -> np.ndarray:
        raise NotImplementedError

    def params(self, tr: Trajectory) -> list[Param]:
        cols = self.columns(tr)
        s = self.scale(tr)[cols]
        nominal = getattr(tr.model, self.field)[tr.dadr[cols]]
        if self.per_joint:
            return [Param(f"added@{tr.log.joint_names[c]}", 0.0, -float(n), 5 * float(v), 0.02 * float(v), self.unit)
                    for c, v, n in zip(cols, s, nominal)]
        return [Param("added", 0.0, -float(nominal.min()), 5 * float(s.max()), 0.02 * float(np.median(s)), self.unit)]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        p = self.params(tr)
        return [np.array([q.x0 + f * (q.hi - q.x0) for q in p]) for f in (0.0, 0.05, 0.2)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        arr = getattr(model, self.field)
        dofs = tr.dadr[self.columns(tr)]
        arr[dofs] = np.maximum(arr[dofs] + self.values(x, tr), 0.0)


class CoulombFriction(DofEffect):
    """Dry friction at the joint (``frictionloss``): gears, seals, bearings."""

    name = family = "coulomb_friction"
    field, unit = "dof_frictionloss", "N·m"

    def scale(self, tr: Trajectory) -> np.ndarray:
        return torque_scale(tr)


class ViscousDamping(DofEffect):
    """Torque proportional to joint speed (``damping``): lubricant, back-EMF."""

    name = family = "viscous_damping"
    field, unit = "dof_damping", "N·m·s/rad"

    def scale(self, tr: Trajectory) -> np.ndarray:
        return torque_scale(tr) / speed_scale(tr)


class Armature(DofEffect):
    """Reflected rotor inertia the model lacks (``armature``)."""

    name = family = "armature"
    field, unit = "dof_armature", "kg·m²"

    def scale(self, tr: Trajectory) -> np.ndarray:
        return inertia_scale(tr)


class GainScale(Effect):
    """The actuator's whole PD output is off by a factor (torque constant, gear ratio,
    firmware gain units)."""

    name, family, touches_model, on_drives = "pd_gain_scale", "pd_gain", True, True

    def params(self, tr: Trajectory) -> list[Param]:
        return self.expand([Param("scale", 1.0, 0.2, 4.0, 0.01, "")], tr)

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        n = len(self.params(tr))
        return [np.full(n, s) for s in (0.6, 1.0, 1.6)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        for acts, s in zip(self.actuators_of(tr, self.columns(tr)), self.values(x, tr)):
            for a in acts:
                model.actuator_gainprm[a, 0] *= s
                model.actuator_biasprm[a, 1:3] *= s
                model.actuator_damping[a] *= s


class TorqueSaturation(Effect):
    """The actuator delivers at most ``limit`` (a fraction of the model's limit, or of
    a typical torque when the model has none): current limits, supply sag."""

    name, family, touches_model, on_drives = "torque_saturation", "torque_saturation", True, True

    def _reference(self, tr: Trajectory) -> np.ndarray:
        m = tr.model
        ref = 4.0 * torque_scale(tr)
        for c, acts in zip(range(len(ref)), self.actuators_of(tr, np.arange(len(ref)))):
            if len(acts) and m.actuator_forcelimited[acts[0]]:
                ref[c] = float(np.max(np.abs(m.actuator_forcerange[acts[0]])))
        return ref

    def params(self, tr: Trajectory) -> list[Param]:
        # down to 0.2 %: a joint loaded far below its model's limit (a humanoid's knee abduction)
        # saturates at a percent of it, which a bound at 2 % left to a PD gain to imitate
        return self.expand([Param("fraction", 1.0, 0.002, 1.0, 0.001, "of limit")], tr)

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        # Geometric: a robot far from its torque limits saturates at a small fraction of them.
        n = len(self.params(tr))
        return [np.full(n, f) for f in (0.006, 0.015, 0.03, 0.08, 0.2, 0.45, 0.8)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        cols = self.columns(tr)
        ref = self._reference(tr)[cols]
        for acts, f, r in zip(self.actuators_of(tr, cols), self.values(x, tr), ref):
            for a in acts:
                model.actuator_forcelimited[a] = 1
                model.actuator_forcerange[a] = (-f * r, f * r)
