"""What every effect is: its parameters, the signals it may edit, the model edits it may make, and
the scales that set its parameters' ranges from a log."""

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


def joint_actuators(tr: Trajectory, cols: np.ndarray) -> list[np.ndarray]:
    """For each logged column in ``cols``, the actuators that drive its joint directly."""
    m = tr.model
    jids = [m.joint(tr.log.joint_names[c]).id for c in cols]
    joint_trn = m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT)
    return [np.flatnonzero(joint_trn & (m.actuator_trnid[:, 0] == j)) for j in jids]


def driven_columns(tr: Trajectory) -> np.ndarray:
    """Indices of the logged joints that an actuator drives directly."""
    cols = np.arange(len(tr.log.joint_names))
    return cols[[len(a) > 0 for a in joint_actuators(tr, cols)]]


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
    gap (``per_joint_allowed`` or ``focus_allowed``); ``below_focus``: also confined to each body
    that joint carries (a link's load shows at the joints that carry it, more than at its own
    joint). ``on_drives``: the effect acts through the actuators (their gains, limits,
    commands), so its joints are only those an actuator drives directly: a per-joint variant
    has no parameter for an unactuated joint (a leg's rail), which nothing it changes could
    move. ``refine``: the number of best start
    points the fit descends from, for effects with several local minima. ``refines``: the
    name of a simpler effect this one elaborates (gearbox friction contains load friction as
    a special case); the diagnosis fits it only where that one, in the same scope, ranks among
    the best, from :meth:`nested_starts`. ``adds_state``: the effect replays on a model with
    parts the log's model lacks (:meth:`extended_model`), whose extra state each window starts
    from :meth:`start_state`.
    """

    name = "effect"
    family = "effect"
    touches_model = False
    changes_inertia = False  # edits masses, centres of mass or inertias: the model's constants are recomputed
    state_friction = False
    adds_state = False  # replays on a model with parts the log's lacks (:meth:`extended_model`)
    per_joint_allowed = True
    focus_allowed = False
    below_focus = False  # also confined to each body below the focus joint's
    on_drives = False  # acts through the actuators: its joints are the driven ones
    refine = 1  # how many of the best start points are descended from (several local minima)
    refines: str | None = None  # the simpler effect this one elaborates (fitted only where that one ranks well)

    def __init__(self, joints: tuple[str, ...] | None = None, per_joint: bool = False) -> None:
        self.joints = joints
        self.per_joint = per_joint

    @property
    def label(self) -> str:
        scope = "shared" if self.joints is None else ",".join(self.joints)
        if self.per_joint:  # one parameter per joint: of every joint, or of those named
            scope = "per-joint" if self.joints is None else f"per-joint: {scope}"
        return f"{self.name}[{scope}]"

    # -- targets -----------------------------------------------------------------------
    def columns(self, tr: Trajectory) -> np.ndarray:
        """Indices of the target joints among the log's joints (of the driven ones only, for an
        effect ``on_drives`` on every joint)."""
        names = tr.log.joint_names
        if self.joints is not None:
            return np.array([names.index(j) for j in self.joints], dtype=int)
        return driven_columns(tr) if self.on_drives else np.arange(len(names))

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
        """Whether the effect can act on this log: one ``on_drives`` needs a driven target joint."""
        return not self.on_drives or any(len(a) for a in joint_actuators(tr, self.columns(tr)))

    def params(self, tr: Trajectory) -> list[Param]:
        raise NotImplementedError

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        """Multi-start points for non-convex fits (default: the start value only)."""
        return [np.array([p.x0 for p in self.params(tr)])]

    def nested_starts(self, simple: np.ndarray, tr: Trajectory) -> list[np.ndarray]:
        """Start points from the fit of the simpler effect this one ``refines``."""
        raise NotImplementedError

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

    def extended_model(self, tr: Trajectory) -> mujoco.MjModel:
        """``tr``'s model with the bodies, joints and tendons this effect adds (only if
        ``adds_state``), which :meth:`edit_model` then edits. The logged joints keep their
        state addresses and the actuators their order."""
        raise NotImplementedError

    def start_state(self, x: np.ndarray, tr: Trajectory, model: mujoco.MjModel, ctrl: np.ndarray,
                    states: np.ndarray, samples: np.ndarray) -> np.ndarray:
        """Full initial states (k, nstate) of ``model`` (the extended model at ``x``) with the
        added state set, given the fine-grid commands (T * nsub, nu), ``states`` with the logged
        joints' state in place and their log ``samples`` (k,) (only if ``adds_state``)."""
        raise NotImplementedError


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


class CannotApply(ValueError):
    """An effect that cannot act on this log (the diagnosis skips it and reports why)."""
