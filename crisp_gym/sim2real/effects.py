"""The library of candidate unmodelled effects.

An effect is a named, parametric change either to the model (friction, damping, gains,
masses, the ground...) or to the signals (a command delay, an encoder bias...). It is
shared by its target joints (one parameter), or per joint (one parameter each).
Adding an effect is one small subclass: say which parameters it has and override
``edit_model`` and/or ``edit_signals`` (and ``measure``, if it acts on the sensor, so
that synthetic logs can be generated with it).

Identification treats delays on the command and on the sensor as one family: when the
servo closes its loop on its own encoder, both shift the response by the same amount in
an open-loop replay and cannot be told apart from position logs.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from crisp_gym.sim2real.replay import Trajectory


@dataclass(frozen=True)
class Param:
    """One scalar parameter: start value, bounds, finite-difference step, unit."""

    name: str
    x0: float
    lo: float
    hi: float
    step: float
    unit: str


@dataclass
class Signals:
    """Per-trajectory signals an effect may transform: fine-grid commands (T*nsub, nu)
    and the log in the model's frame, positions and velocities (T, n)."""

    ctrl: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray


class Effect:
    """Base class. Subclasses set ``name`` and ``family`` and implement :meth:`params`."""

    name = "effect"
    family = "effect"
    touches_model = False
    per_joint_allowed = True

    def __init__(self, joints: tuple[str, ...] | None = None, per_joint: bool = False) -> None:
        self.joints = joints
        self.per_joint = per_joint

    @property
    def label(self) -> str:
        scope = "per-joint" if self.per_joint else ("shared" if self.joints is None else ",".join(self.joints))
        return f"{self.name}[{scope}]"

    # -- targets -----------------------------------------------------------------------
    def columns(self, tr: Trajectory) -> np.ndarray:
        """Indices of the target joints among the log's joints."""
        names = tr.log.joint_names
        if self.joints is None:
            return np.arange(len(names))
        return np.array([names.index(j) for j in self.joints], dtype=int)

    def values(self, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        """One value per target joint: the shared parameter repeated, or one each."""
        cols = self.columns(tr)
        return np.asarray(x, dtype=float) if self.per_joint else np.full(len(cols), float(x[0]))

    def actuators_of(self, tr: Trajectory, cols: np.ndarray) -> list[np.ndarray]:
        """For each target column, the actuators that drive its joint directly."""
        m = tr.model
        jids = [m.joint(tr.log.joint_names[c]).id for c in cols]
        joint_trn = m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT)
        return [np.flatnonzero(joint_trn & (m.actuator_trnid[:, 0] == j)) for j in jids]

    def expand(self, base: list[Param], tr: Trajectory) -> list[Param]:
        """Per-joint copies of a parameter template (named ``<param>@<joint>``)."""
        if not self.per_joint:
            return base
        names = [tr.log.joint_names[c] for c in self.columns(tr)]
        return [Param(f"{p.name}@{n}", p.x0, p.lo, p.hi, p.step, p.unit) for n in names for p in base]

    # -- interface -----------------------------------------------------------------------
    def applicable(self, tr: Trajectory) -> bool:
        return True

    def params(self, tr: Trajectory) -> list[Param]:
        raise NotImplementedError

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        """Multi-start points for non-convex fits (default: the start value only)."""
        return [np.array([p.x0 for p in self.params(tr)])]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        """Change a private copy of the model in place."""

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        """Map commands and logged states to what the model should see."""
        return sig

    def measure(self, qpos: np.ndarray, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        """Map simulated true positions (T, n) to what the sensor reports."""
        return qpos


# -- scales shared by the joint effects ------------------------------------------------------
def torque_scale(tr: Trajectory) -> np.ndarray:
    """A typical actuator torque per logged joint: PD stiffness times the spread of the
    tracking error (at least 0.01 rad), so that bounds and steps suit any robot size."""
    m = tr.model
    out = np.ones(len(tr.log.joint_names))
    err = np.maximum(np.std(_tracking_error(tr), axis=0), 0.01)
    for c, name in enumerate(tr.log.joint_names):
        jid = m.joint(name).id
        acts = np.flatnonzero((m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT)) & (m.actuator_trnid[:, 0] == jid))
        kp = float(sum(abs(m.actuator_biasprm[a, 1]) or abs(m.actuator_gainprm[a, 0]) for a in acts)) or 1.0
        out[c] = kp * err[c]
    return out


def _tracking_error(tr: Trajectory) -> np.ndarray:
    """Command minus position per logged joint where a joint actuator drives it, else the
    position's deviation from its mean."""
    m = tr.model
    err = tr.log.qpos - tr.log.qpos.mean(axis=0)
    for c, name in enumerate(tr.log.joint_names):
        jid = m.joint(name).id
        acts = np.flatnonzero((m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT)) & (m.actuator_trnid[:, 0] == jid))
        if len(acts):
            err[:, c] = tr.ctrl[::tr.nsub, acts[0]] - tr.log.qpos[:, c]
    return err


def inertia_scale(tr: Trajectory) -> np.ndarray:
    """Diagonal of the joint-space inertia at the log's mean posture, per logged joint."""
    m = tr.model
    d = mujoco.MjData(m)
    d.qpos[tr.qadr] = tr.log.qpos.mean(axis=0)
    mujoco.mj_forward(m, d)
    full = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, full)
    return np.diag(full)[tr.dadr].copy()


def speed_scale(tr: Trajectory) -> np.ndarray:
    return np.maximum(np.std(tr.qvel, axis=0), 1e-3)


# -- signal effects -------------------------------------------------------------------------------
def _shift(signal: np.ndarray, shift: float) -> np.ndarray:
    """``signal`` sampled ``shift`` samples later (negative: earlier), linearly
    interpolated and clamped at the ends."""
    n = len(signal)
    pos = np.clip(np.arange(n) - shift, 0, n - 1)
    i0 = np.floor(pos).astype(int)
    i1 = np.minimum(i0 + 1, n - 1)
    w = (pos - i0)[:, None] if signal.ndim == 2 else pos - i0
    return signal[i0] * (1 - w) + signal[i1] * w


class ActuatorDelay(Effect):
    """Commands reach the actuators ``delay`` seconds late (bus, filtering, firmware)."""

    name, family, per_joint_allowed = "actuator_delay", "delay", False

    def params(self, tr: Trajectory) -> list[Param]:
        return [Param("delay", 0.01, 0.0, 0.15, 0.25 * tr.log.dt, "s")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([d]) for d in (0.004, 0.012, 0.025, 0.045, 0.07, 0.1)]

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        h = tr.log.dt / tr.nsub
        return Signals(_shift(sig.ctrl, x[0] / h), sig.qpos, sig.qvel)


class SensorDelay(Effect):
    """The logged position lags the true one by ``delay`` seconds."""

    name, family, per_joint_allowed = "sensor_delay", "delay", False

    def params(self, tr: Trajectory) -> list[Param]:
        return [Param("delay", 0.01, 0.0, 0.15, 0.25 * tr.log.dt, "s")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([d]) for d in (0.004, 0.012, 0.025, 0.045, 0.07, 0.1)]

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        k = x[0] / tr.log.dt
        return Signals(sig.ctrl, _shift(sig.qpos, -k), _shift(sig.qvel, -k))

    def measure(self, qpos: np.ndarray, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        return _shift(qpos, x[0] / tr.log.dt)


class Backlash(Effect):
    """Play between command and joint: the effective target moves only once the command
    has crossed a dead band of half-width ``gap`` (a play operator on the command)."""

    name, family, per_joint_allowed = "backlash", "backlash", False

    def params(self, tr: Trajectory) -> list[Param]:
        return [Param("half_width", 0.01, 0.0, 0.2, 5e-4, "rad")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([b]) for b in (0.003, 0.01, 0.03, 0.08)]

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        acts = np.concatenate(self.actuators_of(tr, self.columns(tr)))
        if not len(acts):
            return sig
        b = x[0]
        u = sig.ctrl[::tr.nsub, acts]
        y = np.empty_like(u)
        y[0] = u[0]
        for k in range(1, len(u)):
            y[k] = np.clip(y[k - 1], u[k] - b, u[k] + b)
        ctrl = sig.ctrl.copy()
        ctrl[:, acts] = np.repeat(y, tr.nsub, axis=0)[:len(ctrl)]
        return Signals(ctrl, sig.qpos, sig.qvel)


class EncoderBias(Effect):
    """A constant offset between the encoder's zero and the model's joint zero."""

    name, family = "encoder_bias", "encoder_bias"

    def params(self, tr: Trajectory) -> list[Param]:
        return self.expand([Param("bias", 0.0, -0.3, 0.3, 1e-3, "rad")], tr)

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        qpos = sig.qpos.copy()
        qpos[:, self.columns(tr)] -= self.values(x, tr)
        return Signals(sig.ctrl, qpos, sig.qvel)

    def measure(self, qpos: np.ndarray, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        out = qpos.copy()
        out[:, self.columns(tr)] += self.values(x, tr)
        return out


# -- joint model effects --------------------------------------------------------------------------
class _DofEffect(Effect):
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


class CoulombFriction(_DofEffect):
    """Dry friction at the joint (``frictionloss``): gears, seals, bearings."""

    name = family = "coulomb_friction"
    field, unit = "dof_frictionloss", "N·m"

    def scale(self, tr: Trajectory) -> np.ndarray:
        return torque_scale(tr)


class ViscousDamping(_DofEffect):
    """Torque proportional to joint speed (``damping``): lubricant, back-EMF."""

    name = family = "viscous_damping"
    field, unit = "dof_damping", "N·m·s/rad"

    def scale(self, tr: Trajectory) -> np.ndarray:
        return torque_scale(tr) / speed_scale(tr)


class Armature(_DofEffect):
    """Reflected rotor inertia the model lacks (``armature``)."""

    name = family = "armature"
    field, unit = "dof_armature", "kg·m²"

    def scale(self, tr: Trajectory) -> np.ndarray:
        return inertia_scale(tr)


class GainScale(Effect):
    """The actuator's whole PD output is off by a factor (torque constant, gear ratio,
    firmware gain units)."""

    name, family, touches_model = "pd_gain_scale", "pd_gain", True

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


class TorqueSaturation(Effect):
    """The actuator delivers at most ``limit`` (a fraction of the model's limit, or of
    a typical torque when the model has none): current limits, supply sag."""

    name, family, touches_model = "torque_saturation", "torque_saturation", True

    def _reference(self, tr: Trajectory) -> np.ndarray:
        m = tr.model
        ref = 4.0 * torque_scale(tr)
        for c, acts in zip(range(len(ref)), self.actuators_of(tr, np.arange(len(ref)))):
            if len(acts) and m.actuator_forcelimited[acts[0]]:
                ref[c] = float(np.max(np.abs(m.actuator_forcerange[acts[0]])))
        return ref

    def params(self, tr: Trajectory) -> list[Param]:
        return self.expand([Param("fraction", 1.0, 0.02, 1.0, 0.005, "of limit")], tr)

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        n = len(self.params(tr))
        return [np.full(n, f) for f in (0.1, 0.25, 0.5, 0.8)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        cols = self.columns(tr)
        ref = self._reference(tr)[cols]
        for acts, f, r in zip(self.actuators_of(tr, cols), self.values(x, tr), ref):
            for a in acts:
                model.actuator_forcelimited[a] = 1
                model.actuator_forcerange[a] = (-f * r, f * r)


class MassScale(Effect):
    """The links are heavier or lighter than modelled (payload, wrong CAD densities):
    masses and inertias of every body moved by a target joint, times ``scale``."""

    name, family, touches_model, per_joint_allowed = "mass_scale", "mass", True, False

    def params(self, tr: Trajectory) -> list[Param]:
        return [Param("scale", 1.0, 0.3, 3.0, 0.01, "")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([s]) for s in (0.7, 1.0, 1.5)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        bodies = _moved_bodies(model, [model.joint(tr.log.joint_names[c]).id for c in self.columns(tr)])
        model.body_mass[bodies] *= x[0]
        model.body_inertia[bodies] *= x[0]


def _moved_bodies(model: mujoco.MjModel, jids: list[int]) -> np.ndarray:
    """Bodies at or below the bodies of the given joints."""
    roots = {int(model.jnt_bodyid[j]) for j in jids}
    moved = []
    for b in range(1, model.nbody):
        a = b
        while a > 0 and a not in roots:
            a = int(model.body_parentid[a])
        if a in roots:
            moved.append(b)
    return np.array(moved, dtype=int)


# -- contact effects ------------------------------------------------------------------------------
def ground_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Colliding geoms of the world body: the floor and any static support."""
    colliding = (model.geom_contype != 0) | (model.geom_conaffinity != 0)
    return np.flatnonzero((model.geom_bodyid == 0) & colliding)


class _GroundEffect(Effect):
    touches_model, per_joint_allowed = True, False

    def applicable(self, tr: Trajectory) -> bool:
        return len(ground_geoms(tr.model)) > 0


class GroundFriction(_GroundEffect):
    """The ground's sliding friction coefficient differs from the model's."""

    name = family = "ground_friction"

    def params(self, tr: Trajectory) -> list[Param]:
        g = ground_geoms(tr.model)
        return [Param("mu", float(tr.model.geom_friction[g[0], 0]), 0.02, 2.5, 0.01, "")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([m]) for m in (0.1, 0.4, 1.0)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        model.geom_friction[ground_geoms(model), 0] = x[0]


class ContactSoftness(_GroundEffect):
    """The ground (or the feet's padding) is softer or stiffer: solref time constant."""

    name = family = "contact_softness"

    def params(self, tr: Trajectory) -> list[Param]:
        g = ground_geoms(tr.model)
        return [Param("timeconst", float(tr.model.geom_solref[g[0], 0]), 0.002, 0.3, 5e-4, "s")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([t]) for t in (0.01, 0.04, 0.1)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        model.geom_solref[ground_geoms(model), 0] = x[0]


class GroundHeight(_GroundEffect):
    """The ground is higher or lower than modelled."""

    name = family = "ground_height"

    def params(self, tr: Trajectory) -> list[Param]:
        return [Param("offset", 0.0, -0.08, 0.08, 2e-4, "m")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([h]) for h in (-0.02, 0.0, 0.02)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        model.geom_pos[ground_geoms(model), 2] += x[0]


class GroundTilt(_GroundEffect):
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


EFFECT_TYPES: tuple[type[Effect], ...] = (
    ActuatorDelay, SensorDelay, CoulombFriction, ViscousDamping, Armature, GainScale, TorqueSaturation,
    Backlash, EncoderBias, MassScale, GroundFriction, ContactSoftness, GroundHeight, GroundTilt,
)
"""Every effect of the library, in the order the report lists them."""

FAMILIES: tuple[str, ...] = tuple(dict.fromkeys(t.family for t in EFFECT_TYPES))


def library(tr: Trajectory, focus: str | None = None, families: tuple[str, ...] | None = None) -> list[Effect]:
    """Candidate effects for a log: each effect shared by all joints; for joint effects
    on a multi-joint log, also one confined to ``focus`` (the joint with the largest gap)
    and one with a parameter per joint. Effects that cannot act (no ground) are left out."""
    out: list[Effect] = []
    n = len(tr.log.joint_names)
    for kind in EFFECT_TYPES:
        if families is not None and kind.family not in families:
            continue
        variants = [kind()]
        if n > 1 and kind.per_joint_allowed:
            if focus is not None:
                variants.append(kind(joints=(focus,)))
            variants.append(kind(per_joint=True))
        elif n > 1 and focus is not None and kind is MassScale:
            variants.append(kind(joints=(focus,)))
        out.extend(v for v in variants if v.applicable(tr))
    return out
