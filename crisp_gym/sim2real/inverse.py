"""Every joint's friction, damping and armature at once, from the torque the logged motion needed.

The classical linear identification of a robot's joint model (inverse dynamic identification
model, least squares). Along the logged motion, smoothed and differentiated twice, MuJoCo's
inverse dynamics gives the torque each joint needed to move as logged; the actuators' torque at
the logged commands minus that need is what the joint's own losses took. Per joint that
difference is linear in four terms the library has as effects:

=======================  ============================  ===================================
term                     regressor                     effect
=======================  ============================  ===================================
Coulomb friction         sign(v)                       :class:`~.effects.CoulombFriction`
viscous damping          v                             :class:`~.effects.ViscousDamping`
armature (added)         acceleration                  :class:`~.effects.Armature`
load-dependent friction  sign(v) × |actuator torque|   :class:`~.effects.LoadFriction`
=======================  ============================  ===================================

so one bounded least-squares solve per joint estimates all of them, for every joint, in a
fraction of a second. Replay fits cannot afford that search: one family per joint is what a
per-joint mixture tries. The estimate is a start, not a verdict: smoothing biases its armature,
and frictionloss sticks where sign(v) only flips. The diagnosis fits
the four per-joint effects by replay from it, prunes those the held-out data do not need, and
ranks what remains with every other candidate.

It needs every degree of freedom of the model in the log (a floating base or an unlogged joint
leaves the needed torque unknown) and drops the samples at which a joint's subtree touches the
world (the contact force is not in the log).
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.optimize import lsq_linear
from scipy.signal import savgol_filter

from crisp_gym.sim2real.effects import Armature, CannotApply, CoulombFriction, LoadFriction, ViscousDamping
from crisp_gym.sim2real.effects.base import Effect
from crisp_gym.sim2real.effects.loads import actuator_torque
from crisp_gym.sim2real.gap import contact_mask
from crisp_gym.sim2real.replay import Trajectory

SLOW_FRACTION = 0.1
"""Samples slower than this fraction of a joint's speed spread are left out of its regression: a
joint held by its dry friction (stuck) takes less than the full friction, which sign(v) cannot say."""

JOINT_MODEL: tuple[type[Effect], ...] = (CoulombFriction, ViscousDamping, Armature, LoadFriction)
"""The per-joint effects the regression estimates, in the order of its columns."""


def smoothed_motion(tr: Trajectory, window_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, velocities and accelerations (T, n) from a cubic Savitzky-Golay fit over
    ``window_s`` seconds (at least 5 samples)."""
    dt, q = tr.log.dt, tr.log.qpos
    width = 2 * half_window(dt, window_s) + 1
    if len(q) < width:
        raise CannotApply(f"the log has {len(q)} samples, fewer than the {width} its derivatives need")
    fit = [smooth(q, dt, window_s, deriv=k) for k in range(3)]
    return fit[0], fit[1], fit[2]


def half_window(dt: float, window_s: float) -> int:
    """Samples on each side of the centre of a smoothing window of ``window_s`` seconds (at least 2)."""
    return max(2, int(round(window_s / (2 * dt))))


def smooth(x: np.ndarray, dt: float, window_s: float, deriv: int = 0) -> np.ndarray:
    """A cubic Savitzky-Golay fit of ``x`` (T, ...) over ``window_s`` seconds, or its ``deriv``-th derivative."""
    return savgol_filter(x, 2 * half_window(dt, window_s) + 1, 3, deriv=deriv, delta=dt, axis=0)


def implicit_lead(model: mujoco.MjModel) -> float:
    """How far ahead (s) the integrator evaluates velocity-dependent forces: one timestep for the
    implicit ones, which damp with the velocity at the step's end. A servo's damping kd then acts
    as kd x timestep of extra inertia in the replay, which the regression would put on the armature."""
    implicit = (mujoco.mjtIntegrator.mjINT_IMPLICIT, mujoco.mjtIntegrator.mjINT_IMPLICITFAST)
    return float(model.opt.timestep) if model.opt.integrator in implicit else 0.0


def needed_torque(tr: Trajectory, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """(T, n) torque each logged joint needs to follow ``q, v, a`` on the model without its
    logged joints' damping and dry friction (those are regressed, not assumed)."""
    model = tr.model.__copy__()
    model.dof_damping[tr.dadr] = 0.0
    model.dof_frictionloss[tr.dadr] = 0.0
    data = mujoco.MjData(model)
    out = np.empty(q.shape)
    for k in range(len(q)):
        data.qpos[tr.qadr], data.qvel[tr.dadr], data.qacc[tr.dadr] = q[k], v[k], a[k]
        mujoco.mj_inverse(model, data)
        out[k] = data.qfrc_inverse[tr.dadr]
    return out


def estimate_joint_model(trajs: list[Trajectory], window_s: float = 0.05) -> np.ndarray:
    """(n, 4) per logged joint: total Coulomb friction (N·m), total viscous damping
    (N·m·s/rad), armature to add to the model's (kg·m²) and load-dependent friction (N·m per
    N·m), the columns of :data:`JOINT_MODEL`; frictions and damping non-negative, the armature
    not below minus the model's. Raises :class:`CannotApply` when the model has a degree of
    freedom the log lacks or a joint has no contact-free moving sample."""
    ref = trajs[0]
    if len(ref.dadr) != ref.model.nv:
        raise CannotApply(f"the model has {ref.model.nv} degrees of freedom and the log {len(ref.dadr)}: "
                          "the torque the motion needed is unknown")
    rows: list[np.ndarray] = []
    extra: list[np.ndarray] = []
    keep: list[np.ndarray] = []
    for tr in trajs:
        q, v, a = smoothed_motion(tr, window_s)
        # the command the motion around each sample saw (the interval before it and the one after),
        # smoothed as the motion is: the drive's torque is then filtered as the need is
        held = tr.ctrl[::tr.nsub][:len(q)]
        ctrl = smooth(0.5 * (np.vstack([held[:1], held[:-1]]) + held), tr.log.dt, window_s)
        cols = np.arange(len(tr.dadr))
        drive = actuator_torque(tr.model, tr, cols, ctrl, tr.enabled, q, v + implicit_lead(tr.model) * a)
        extra.append(drive - needed_torque(tr, q, v, a))
        rows.append(np.stack([np.sign(v), v, a, np.sign(v) * np.abs(drive)], axis=-1))
        inside = np.ones(q.shape, dtype=bool)
        trim = half_window(tr.log.dt, window_s)  # the fit's ends extrapolate
        inside[:trim] = inside[-trim:] = False
        touching = contact_mask(tr)
        keep.append(inside if touching is None else inside & ~touching)
    X, y, ok = np.concatenate(rows), np.concatenate(extra), np.concatenate(keep)
    out = np.empty((len(ref.dadr), len(JOINT_MODEL)))
    for j, dof in enumerate(ref.dadr):
        use = ok[:, j] & (np.abs(X[:, j, 1]) > SLOW_FRACTION * np.std(X[:, j, 1]))
        if use.sum() < 2 * len(JOINT_MODEL):
            raise CannotApply(f"joint {ref.log.joint_names[j]} has no contact-free moving samples to regress on")
        lo = np.array([0.0, 0.0, -float(ref.model.dof_armature[dof]), 0.0])
        active = np.any(X[use, j] != 0.0, axis=0)  # an undriven joint has no load term
        out[j] = 0.0
        out[j, active] = lsq_linear(X[use, j][:, active], y[use, j], bounds=(lo[active], np.inf)).x
    return out


def joint_model_start(trajs: list[Trajectory], effects: tuple[Effect, ...], window_s: float = 0.05) -> np.ndarray:
    """The parameters of ``effects`` (per-joint instances of :data:`JOINT_MODEL`, in its order)
    at the regression's estimate: added to the model's values where the effect adds, clipped to
    each parameter's bounds."""
    ref = trajs[0]
    terms = estimate_joint_model(trajs, window_s)
    nominal = [ref.model.dof_frictionloss[ref.dadr], ref.model.dof_damping[ref.dadr], 0.0, 0.0]
    x = np.concatenate([terms[e.columns(ref), k] - np.broadcast_to(nominal[k], len(ref.dadr))[e.columns(ref)]
                        for k, e in enumerate(effects)])
    params = [p for e in effects for p in e.params(ref)]
    return np.clip(x, [p.lo for p in params], [p.hi for p in params])
