"""The library of candidate unmodelled effects.

An effect is a named, parametric change either to the model (friction, damping, gains,
masses, the ground...) or to the signals (a command delay, an encoder bias...). It is
shared by its target joints (one parameter), or per joint (one parameter each).
Adding an effect is one small subclass: say which parameters it has and override
``edit_model`` and/or ``edit_signals`` (and ``measure``, if it acts on the sensor, so
that synthetic logs can be generated with it), or ``friction`` for dry friction that
depends on the state (load-dependent and Stribeck friction; the replay then steps the
model one log sample at a time).

Identification treats delays on the command and on the sensor as one family: when the
servo closes its loop on its own encoder, both shift the response by the same amount in
an open-loop replay and cannot be told apart from position logs.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from crisp_gym.sim2real.models import SUPPORT_SLOT, lowest_point
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


def joint_actuators(tr: Trajectory, cols: np.ndarray) -> list[np.ndarray]:
    """For each logged column in ``cols``, the actuators that drive its joint directly."""
    m = tr.model
    jids = [m.joint(tr.log.joint_names[c]).id for c in cols]
    joint_trn = m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT)
    return [np.flatnonzero(joint_trn & (m.actuator_trnid[:, 0] == j)) for j in jids]


@dataclass
class Signals:
    """Per-trajectory signals an effect may transform: fine-grid commands (T*nsub, nu)
    and the log in the model's frame, positions and velocities (T, n)."""

    ctrl: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray


class Effect:
    """Base class. Subclasses set ``name`` and ``family`` and implement :meth:`params`.

    Scopes: every effect is tried shared by all joints; on multi-joint logs also with one
    parameter per joint (``per_joint_allowed``) and confined to the joint with the largest
    gap (``per_joint_allowed`` or ``focus_allowed``). ``refine``: the number of best start
    points the fit descends from, for effects with several local minima.
    """

    name = "effect"
    family = "effect"
    touches_model = False
    state_friction = False
    per_joint_allowed = True
    focus_allowed = False
    refine = 1  # how many of the best start points are descended from (several local minima)

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
        return joint_actuators(tr, cols)

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

    def measure_velocity(self, qvel: np.ndarray, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        """Map simulated true velocities (T, n) to what the sensor reports (logs with velocities)."""
        return qvel

    def friction(self, x: np.ndarray, tr: Trajectory, model: mujoco.MjModel, ctrl: np.ndarray, enabled: np.ndarray,
                 qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """Dry friction (k, n) added to the logged joints at k states, given the commands
        (k, nu) and powered actuators (k, nu) there (only if ``state_friction``)."""
        raise NotImplementedError


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
    """Commands reach the actuators ``delay`` seconds late (bus, filtering, firmware): all of
    them, or (confined to a joint) only the drives of that joint, as one slow servo on a bus."""

    name, family, per_joint_allowed, focus_allowed = "actuator_delay", "delay", False, True

    def params(self, tr: Trajectory) -> list[Param]:
        return [Param("delay", 0.01, 0.0, 0.15, 0.25 * tr.log.dt, "s")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([d]) for d in (0.004, 0.012, 0.025, 0.045, 0.07, 0.1)]

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        delayed = _shift(sig.ctrl, x[0] * tr.nsub / tr.log.dt)
        if self.joints is None:
            return Signals(delayed, sig.qpos, sig.qvel)
        drives = np.concatenate(self.actuators_of(tr, self.columns(tr)))
        ctrl = sig.ctrl.copy()
        ctrl[:, drives] = delayed[:, drives]
        return Signals(ctrl, sig.qpos, sig.qvel)


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

    def measure_velocity(self, qvel: np.ndarray, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        return _shift(qvel, x[0] / tr.log.dt)


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

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        # Not convex once contacts are involved: a biased leg starts its windows in or above the ground.
        n = len(self.params(tr))
        return [np.full(n, b) for b in (0.0, -0.01, 0.01, -0.03, 0.03, -0.06, 0.06)]

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
        # Geometric: a robot far from its torque limits saturates at a small fraction of them.
        n = len(self.params(tr))
        return [np.full(n, f) for f in (0.03, 0.08, 0.2, 0.45, 0.8)]

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

    name, family, touches_model, per_joint_allowed, focus_allowed = "mass_scale", "mass", True, False, True

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


class ComShift(Effect):
    """The link's centre of mass is off (payload mounted off-centre, wrong CAD): the COM
    of each target joint's body moves ``along`` the lever (joint axis to COM) and
    ``across`` it, in the plane normal to the joint axis (the axial part has no effect)."""

    name, family, touches_model, per_joint_allowed, focus_allowed = "com_shift", "mass", True, False, True

    def params(self, tr: Trajectory) -> list[Param]:
        reach = max(2.0 * float(lever_scale(tr)[self.columns(tr)].max()), 0.05)
        return [Param("along", 0.0, -reach, reach, 1e-4, "m"), Param("across", 0.0, -reach, reach, 1e-4, "m")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        r = 0.1 * float(lever_scale(tr)[self.columns(tr)].max())
        return [np.array([a, b]) for a in (-r, r) for b in (-r, r)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        for c in self.columns(tr):
            jid = model.joint(tr.log.joint_names[c]).id
            along, across = _lever_frame(model, jid)
            model.body_ipos[model.jnt_bodyid[jid]] += x[0] * along + x[1] * across


def _lever(model: mujoco.MjModel, jid: int) -> tuple[np.ndarray, np.ndarray]:
    """The joint's unit axis and its lever: the vector from the axis to the COM of the
    joint's body, normal to the axis (both in the body frame)."""
    axis = model.jnt_axis[jid] / np.linalg.norm(model.jnt_axis[jid])
    r = model.body_ipos[model.jnt_bodyid[jid]] - model.jnt_pos[jid]
    return axis, r - (r @ axis) * axis


def _lever_frame(model: mujoco.MjModel, jid: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors, in the joint's body frame, along the lever and across it."""
    axis, r = _lever(model, jid)
    if np.linalg.norm(r) < 1e-6:  # COM on the axis: any normal direction will do
        r = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    along = r / np.linalg.norm(r)
    return along, np.cross(axis, along)


def lever_scale(tr: Trajectory) -> np.ndarray:
    """Per logged joint, the length of its lever (:func:`_lever`), at least 1 cm."""
    return np.array([max(float(np.linalg.norm(_lever(tr.model, tr.model.joint(n).id)[1])), 0.01)
                     for n in tr.log.joint_names])


# -- state-dependent friction ---------------------------------------------------------------------
def actuator_torque(model: mujoco.MjModel, tr: Trajectory, cols: np.ndarray, ctrl: np.ndarray, enabled: np.ndarray,
                    qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """(k, len(cols)) torque the joint actuators apply to each target joint at the given
    states: the affine actuator law (gain x ctrl + bias), clamped to its force range, zero
    where the actuator is off. This is the torque the gear train transmits."""
    out = np.zeros((len(ctrl), len(cols)))
    for i, (c, acts) in enumerate(zip(cols, joint_actuators(tr, cols))):
        for a in acts:
            gear = model.actuator_gear[a, 0]
            force = (model.actuator_gainprm[a, 0] * ctrl[:, a] + model.actuator_biasprm[a, 0]
                     + model.actuator_biasprm[a, 1] * gear * qpos[:, c] + model.actuator_biasprm[a, 2] * gear * qvel[:, c])
            if model.actuator_forcelimited[a]:
                force = np.clip(force, *model.actuator_forcerange[a])
            out[:, i] += gear * force * enabled[:, a]
    return out


class LoadFriction(Effect):
    """Gear friction that grows with the torque the gear train transmits (BAM's
    load-dependent friction): up to ``mu`` x |actuator torque| of dry friction. Under
    load it holds the joint still long after the command has moved (stick phases that
    Coulomb + viscous friction cannot reproduce)."""

    name = family = "load_friction"
    state_friction = True

    def params(self, tr: Trajectory) -> list[Param]:
        return self.expand([Param("mu", 0.0, 0.0, 0.95, 0.005, "N·m per N·m")], tr)

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        n = len(self.params(tr))
        return [np.full(n, m) for m in (0.05, 0.15, 0.4)]

    def friction(self, x: np.ndarray, tr: Trajectory, model: mujoco.MjModel, ctrl: np.ndarray, enabled: np.ndarray,
                 qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        cols = self.columns(tr)
        out = np.zeros(qpos.shape)
        out[:, cols] = self.values(x, tr) * np.abs(actuator_torque(model, tr, cols, ctrl, enabled, qpos, qvel))
        return out


class StribeckFriction(Effect):
    """Extra dry friction near rest that fades with speed (Stribeck effect): ``static``
    x exp(-(v / ``velocity``)^2) on top of the model's friction: breakaway is harder than
    sliding."""

    name = family = "stribeck_friction"
    state_friction, per_joint_allowed, focus_allowed = True, False, True

    def params(self, tr: Trajectory) -> list[Param]:
        cols = self.columns(tr)
        ts = float(torque_scale(tr)[cols].max())
        vs = float(speed_scale(tr)[cols].max())
        return [Param("static", 0.0, 0.0, 5 * ts, 0.02 * ts, "N·m"),
                Param("velocity", 0.2 * vs, 0.02 * vs, 2 * vs, 0.005 * vs, "rad/s")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        cols = self.columns(tr)
        ts = float(torque_scale(tr)[cols].max())
        vs = float(speed_scale(tr)[cols].max())
        return [np.array([f * ts, v * vs]) for f in (0.1, 0.4) for v in (0.1, 0.4)]

    def friction(self, x: np.ndarray, tr: Trajectory, model: mujoco.MjModel, ctrl: np.ndarray, enabled: np.ndarray,
                 qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        cols = self.columns(tr)
        out = np.zeros(qpos.shape)
        out[:, cols] = x[0] * np.exp(-(qvel[:, cols] / x[1]) ** 2)
        return out


# -- contact effects ------------------------------------------------------------------------------
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


class SupportBox(_GroundEffect):
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


class CannotApply(ValueError):
    """An effect that cannot act on this log (the diagnosis skips it and reports why)."""


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


EFFECT_TYPES: tuple[type[Effect], ...] = (
    ActuatorDelay, SensorDelay, CoulombFriction, ViscousDamping, Armature, GainScale, TorqueSaturation,
    Backlash, EncoderBias, MassScale, ComShift, LoadFriction, StribeckFriction, GroundFriction, ContactSoftness,
    GroundHeight, GroundTilt, SupportBox,
)
"""Every effect of the library, in the order the report lists them."""

FAMILIES: tuple[str, ...] = tuple(dict.fromkeys(t.family for t in EFFECT_TYPES))


def check_families(families: tuple[str, ...]) -> None:
    """ValueError naming every entry of ``families`` that is no family of :data:`FAMILIES`."""
    unknown = [f for f in families if f not in FAMILIES]
    if unknown:
        raise ValueError(f"unknown effect families {unknown}; the library's are {', '.join(FAMILIES)}")


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
        if n > 1 and focus is not None and (kind.per_joint_allowed or kind.focus_allowed):
            variants.append(kind(joints=(focus,)))
        if n > 1 and kind.per_joint_allowed:
            variants.append(kind(per_joint=True))
        out.extend(v for v in variants if v.applicable(tr))
    return out
