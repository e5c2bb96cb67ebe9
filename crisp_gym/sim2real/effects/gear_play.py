"""Play in a gear train, modelled as the real mechanism: a rotor for the motor, and a gap."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from crisp_gym.sim2real.effects.base import CannotApply, Effect, Param, inertia_scale, joint_actuators
from crisp_gym.sim2real.effects.signals import HALF_WIDTH, HALF_WIDTH_STARTS
from crisp_gym.sim2real.replay import Trajectory

_ROTOR_SHARE = 0.01  # a joint without armature: its rotor's inertia, as a share of the joint's own


@dataclass(frozen=True)
class _Rotors:
    """Where an extended model keeps its rotors: per geared joint, its logged column, the
    rotor's position and velocity addresses, the play tendon and the actuators that drive it."""

    cols: np.ndarray
    qadr: np.ndarray
    dadr: np.ndarray
    tendons: np.ndarray
    actuators: list[np.ndarray]


def add_rotors(spec: mujoco.MjSpec, joints: list[str], inertia: list[float], timestep: float) -> None:
    """Put a gear with play between every joint of ``joints`` and its actuators (``spec``, in place).

    Each joint gets a rotor: a hinge on the world of inertia ``inertia`` (its armature, the
    motor's reflected inertia, moves there). The joint's actuators drive the rotor instead, and a
    tendon (rotor minus joint, named ``<joint>_play``) limited to the gap's half-width couples
    the two; the limit is as stiff as ``timestep`` allows, so the rotor strikes the gap's ends."""
    for joint, rotor_inertia in zip(joints, inertia):
        target = spec.joint(joint)
        name = f"{joint}_rotor"
        # no geometry and a negligible mass at the world origin: only the hinge's armature counts
        body = spec.worldbody.add_body(name=name, mass=1e-6, inertia=[1e-9] * 3, explicitinertial=True)
        body.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1], armature=rotor_inertia)
        target.armature = 0.0
        for actuator in spec.actuators:
            if actuator.target == joint:
                actuator.target = name
        gap = spec.add_tendon(name=f"{joint}_play", limited=mujoco.mjtLimited.mjLIMITED_TRUE,
                              range=[-HALF_WIDTH.x0, HALF_WIDTH.x0], solref_limit=[2 * timestep, 1.0])
        gap.wrap_joint(name, 1.0)
        gap.wrap_joint(joint, -1.0)


class GearPlay(Effect):
    """Play in the gear train between the motor and the joint, of half-width ``half_width``.

    The actuators turn a rotor (the motor, carrying the joint's armature), which drives the
    joint only while it presses on one end of the gap. Inside the gap the joint feels no motor
    torque and the rotor turns freely until it strikes the other end. The side it presses on
    flips with the sign of the torque the gear transmits, not with the command's direction as
    the play operator of :class:`~crisp_gym.sim2real.effects.signals.Backlash` does. A joint
    without armature gets a rotor of 1 % of its own inertia.

    The rotor is a part added to the model, so this effect needs the model as an ``MjSpec``
    (otherwise the diagnosis skips it and says so). Replay windows start each rotor where
    :func:`rotor_track` has it.
    """

    name, family, per_joint_allowed, focus_allowed, on_drives = "gear_play", "backlash", False, True, True
    touches_model = adds_state = True

    def __init__(self, joints: tuple[str, ...] | None = None, per_joint: bool = False) -> None:
        super().__init__(joints, per_joint)
        self._extended: dict[int, tuple[mujoco.MjSpec, mujoco.MjModel, _Rotors]] = {}

    def params(self, tr: Trajectory) -> list[Param]:
        return [HALF_WIDTH]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([b]) for b in HALF_WIDTH_STARTS]

    def _build(self, tr: Trajectory) -> tuple[mujoco.MjSpec, mujoco.MjModel, _Rotors]:
        """The extended model of ``tr``'s spec, built once per spec (resynthesised logs share it)."""
        if tr.spec is None:
            raise CannotApply("gear play adds a rotor to the model: pass the model as an MjSpec")
        key = id(tr.spec)
        if key not in self._extended:
            cols = self.columns(tr)
            names = [tr.log.joint_names[c] for c in cols]
            armature = tr.model.dof_armature[tr.dadr[cols]]
            inertia = np.where(armature > 0, armature, _ROTOR_SHARE * inertia_scale(tr)[cols])
            spec = tr.spec.copy()
            add_rotors(spec, names, list(inertia), tr.model.opt.timestep)
            model = spec.compile()
            model.opt.timestep = tr.model.opt.timestep
            nq, nv = tr.model.nq, tr.model.nv
            if (model.nu != tr.model.nu or not np.array_equal(model.jnt_qposadr[:tr.model.njnt], tr.model.jnt_qposadr)
                    or model.nq != nq + len(cols) or model.nv != nv + len(cols)):
                raise CannotApply("the model compiled from its spec does not match the log's model")
            rotors = _Rotors(np.array(cols), np.array([model.jnt_qposadr[model.joint(f"{n}_rotor").id] for n in names]),
                             np.array([model.jnt_dofadr[model.joint(f"{n}_rotor").id] for n in names]),
                             np.array([model.tendon(f"{n}_play").id for n in names]),
                             joint_actuators(tr, np.array(cols)))
            self._extended[key] = tr.spec, model, rotors  # the spec held so that its id stays unique
        return self._extended[key]

    def extended_model(self, tr: Trajectory) -> mujoco.MjModel:
        return self._build(tr)[1]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        tendons = self._build(tr)[2].tendons
        model.tendon_range[tendons] = [-x[0], x[0]]

    def start_state(self, x: np.ndarray, tr: Trajectory, model: mujoco.MjModel, ctrl: np.ndarray,
                    states: np.ndarray, samples: np.ndarray) -> np.ndarray:
        # Where a rotor is inside its gap is not in the log: it is tracked through the log by
        # rotor_track, each rotor alone against its joint's logged motion.
        rotors = self._build(tr)[2]
        offset, speed = rotor_track(x[0], tr, model, ctrl, rotors.cols, rotors.dadr, rotors.actuators,
                                    limit_compliance(model, rotors.tendons),
                                    last=int(samples.max()))  # the samples after the last start are not needed
        nq1 = 1 + model.nq
        out = states.copy()
        for i, (c, rq, rd) in enumerate(zip(rotors.cols, rotors.qadr, rotors.dadr)):
            out[:, 1 + rq] = states[:, 1 + tr.qadr[c]] + offset[samples, i]
            out[:, nq1 + rd] = speed[samples, i]
        return out


def limit_compliance(model: mujoco.MjModel, tendons: np.ndarray) -> np.ndarray:
    """(R,) how far each tendon's limit yields per unit of force it holds (rad per N·m).

    MuJoCo's limits are soft: at rest a limit holding force ``f`` is pressed in by
    ``f · R / (k · d)``, with impedance ``d`` (``solimp``'s second value, that of a deep
    penetration), stiffness ``k = 1 / (d² τ² ζ²)`` from ``solref = (τ, ζ)`` (τ at least two
    time steps, as MuJoCo clamps it) and regulariser ``R = (1 - d) / d`` times the tendon's
    inverse weight. At a 120 Hz step a light rotor's gap end yields by as much as the gap's
    half-width under a drive's load."""
    tau, zeta = model.tendon_solref_lim[tendons].T
    if np.any(tau <= 0):
        raise ValueError("limit_compliance takes limits given by time constant and damping ratio (solref > 0)")
    d = model.tendon_solimp_lim[tendons, 1]
    stiffness = 1.0 / (d**2 * np.maximum(tau, 2 * model.opt.timestep) ** 2 * zeta**2)
    return (1 - d) / d * model.tendon_invweight0[tendons] / (stiffness * d)


def rotor_track(half_width: float, tr: Trajectory, model: mujoco.MjModel, ctrl: np.ndarray, cols: np.ndarray,
                rotor_dofs: np.ndarray, actuators: list[np.ndarray], compliance: np.ndarray,
                last: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(T, R) each rotor's place in its gap (rotor minus joint) and its speed at every log sample
    up to ``last`` (default: the log's last; T = last + 1), integrated at the log's rate from its
    drive's law on the logged commands (``ctrl``, fine grid), the joint following its log.
    Inside the gap a rotor turns under its drive alone (the drive's stiffness and damping taken
    implicitly; a saturated drive's clamped force with only its passive damping, the drives of
    one joint clamped together); at either end it moves with the joint, pressed into the end by
    ``compliance`` (:func:`limit_compliance`) times the force its drive holds there. It starts
    where the drive's force balance puts it."""
    end = len(tr.log.time) if last is None else last + 1
    dt, q, v = tr.log.dt, tr.log.qpos[:end, cols], tr.qvel[:end, cols]
    u, enabled = ctrl[::tr.nsub][:end], tr.enabled[:end]
    # each rotor's drives summed: force = drive - stiff * theta - damp * omega (all (T, R))
    drive, stiff, damp = (np.zeros(q.shape) for _ in range(3))
    passive, lo, hi = np.zeros(len(cols)), np.full(len(cols), -np.inf), np.full(len(cols), np.inf)
    for i, acts in enumerate(actuators):
        gear, on = model.actuator_gear[acts, 0], enabled[:, acts]
        law = model.actuator_gainprm[acts, 0] * u[:, acts] + model.actuator_biasprm[acts, 0]
        drive[:, i] = np.sum(law * gear * on, axis=1)
        stiff[:, i] = np.sum(-model.actuator_biasprm[acts, 1] * gear**2 * on, axis=1)
        damp[:, i] = np.sum(-model.actuator_biasprm[acts, 2] * gear**2 * on, axis=1)
        passive[i] = np.sum(model.actuator_damping[acts] * gear**2)
        if model.actuator_forcelimited[acts].all():
            lo[i], hi[i] = np.sum(model.actuator_forcerange[acts] * gear[:, None], axis=0)
    inertia = model.dof_armature[rotor_dofs] + 1e-12
    balance = np.divide(drive[0], stiff[0], out=q[0].copy(), where=stiff[0] > 0)
    theta, omega = q[0] + np.clip(balance - q[0], -half_width, half_width), v[0].copy()
    offset, speed = np.empty(q.shape), np.empty(q.shape)
    offset[0], speed[0] = theta - q[0], omega
    for t in range(1, len(q)):
        k, c = stiff[t], damp[t] + passive
        free = (inertia * omega + dt * (drive[t] - k * theta)) / (inertia + dt * c + dt * dt * k)
        force = drive[t] - k * (theta + dt * free) - damp[t] * free
        clamped = (inertia * omega + dt * np.clip(force, lo, hi)) / (inertia + dt * passive)
        omega = np.where((force < lo) | (force > hi), clamped, free)
        theta = theta + dt * omega
        rel = theta - q[t]
        at_end = np.abs(rel) > half_width  # at an end of the gap: the rotor moves with the joint
        side = np.sign(rel)
        # the force that presses it into that end, the end yielding by compliance x force
        held = np.clip((drive[t] - k * (q[t] + side * half_width) - damp[t] * v[t]) / (1 + k * compliance), lo, hi)
        press = compliance * np.maximum(side * (held - passive * v[t]), 0.0)
        theta = np.where(at_end, q[t] + side * (half_width + press), theta)
        omega = np.where(at_end, v[t], omega)
        offset[t], speed[t] = theta - q[t], omega
    return offset, speed
