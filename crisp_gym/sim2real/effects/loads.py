"""Effects of the load the joints carry: mass scale, a shifted centre of mass, a payload, and dry
friction that grows with the load (load-dependent, with BAM's directional and Stribeck load terms)
or falls with speed (Stribeck)."""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from crisp_gym.sim2real.effects.base import Effect, Param, joint_actuators, speed_scale, torque_scale
from crisp_gym.sim2real.replay import Trajectory


class MassScale(Effect):
    """The links are heavier or lighter than modelled (payload, wrong CAD densities):
    masses and inertias of every body moved by a target joint, times ``scale``. Besides the
    focus joint, tried from each body below it: a light wrist shows most at the elbow."""

    name, family, touches_model, per_joint_allowed, focus_allowed = "mass_scale", "mass", True, False, True
    changes_inertia = below_focus = True

    def params(self, tr: Trajectory) -> list[Param]:
        return [Param("scale", 1.0, 0.3, 3.0, 0.01, "")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([s]) for s in (0.7, 1.0, 1.5)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        bodies = _moved_bodies(model, [model.joint(tr.log.joint_names[c]).id for c in self.columns(tr)])
        model.body_mass[bodies] *= x[0]
        model.body_inertia[bodies] *= x[0]


def joints_below(tr: Trajectory, joint: str) -> list[str]:
    """The logged joints of the bodies below ``joint``'s body, one per body (the first logged
    of a body's joints: the others move the same bodies), in the log's order."""
    model = tr.model
    top = int(model.jnt_bodyid[model.joint(joint).id])
    below = set(_moved_bodies(model, [model.joint(joint).id]).tolist()) - {top}
    out = []
    for name in tr.log.joint_names:
        body = int(model.jnt_bodyid[model.joint(name).id])
        if body in below:
            below.discard(body)
            out.append(name)
    return out


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
    changes_inertia = True

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
            body = model.jnt_bodyid[jid]
            release_inertial_frame(model, body)
            model.body_ipos[body] += x[0] * along + x[1] * across


class Payload(Effect):
    """A load the model lacks at the tool (a gripper, a tool, a sensor, a carried part): a point
    mass ``mass`` at ``x, y, z`` in the frame of the last body the target joints move, added to
    that body's mass, centre of mass and inertia. An offset along a joint's own axis changes no
    torque of that joint but those of the joints above it."""

    name, family, touches_model, per_joint_allowed, focus_allowed = "payload", "mass", True, False, True
    changes_inertia = True

    def _tool(self, model: mujoco.MjModel, tr: Trajectory) -> int:
        """The deepest body the target joints move (the end of their chain)."""
        bodies = _moved_bodies(model, [model.joint(tr.log.joint_names[c]).id for c in self.columns(tr)])
        return int(max(bodies, key=lambda b: (_depth(model, b), b)))

    def _scales(self, tr: Trajectory) -> tuple[float, float]:
        """The mass the target joints move (kg) and a reach (m): the longest lever, at least 5 cm."""
        m = tr.model
        moved = _moved_bodies(m, [m.joint(tr.log.joint_names[c]).id for c in self.columns(tr)])
        return float(m.body_mass[moved].sum()), max(float(lever_scale(tr)[self.columns(tr)].max()), 0.05)

    def params(self, tr: Trajectory) -> list[Param]:
        mass, reach = self._scales(tr)
        offset = [Param(axis, 0.0, -3 * reach, 3 * reach, 1e-3 * reach, "m") for axis in ("x", "y", "z")]
        return [Param("mass", 0.0, 0.0, 3.0 * mass, 0.01 * mass, "kg"), *offset]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        mass, _ = self._scales(tr)
        com = tr.model.body_ipos[self._tool(tr.model, tr)]
        return [np.array([f * mass, *com]) for f in (0.2, 0.6)]

    def edit_model(self, model: mujoco.MjModel, x: np.ndarray, tr: Trajectory) -> None:
        b = self._tool(model, tr)
        add_point_mass(model, b, float(x[0]), np.asarray(x[1:4], dtype=float))


def _depth(model: mujoco.MjModel, body: int) -> int:
    depth = 0
    while body > 0:
        body, depth = int(model.body_parentid[body]), depth + 1
    return depth


def add_point_mass(model: mujoco.MjModel, body: int, mass: float, point: np.ndarray) -> None:
    """Add a point mass at ``point`` (body frame) to ``body``: its mass, centre of mass and
    inertia (parallel-axis theorem; the new principal axes become its inertial frame)."""
    if mass <= 0:
        return
    m0, c0 = float(model.body_mass[body]), model.body_ipos[body].copy()
    rot = Rotation.from_quat(model.body_iquat[body], scalar_first=True).as_matrix()
    inertia = rot @ np.diag(model.body_inertia[body]) @ rot.T
    m1 = m0 + mass
    c1 = (m0 * c0 + mass * point) / m1
    for m, d in ((m0, c0 - c1), (mass, point - c1)):
        inertia = inertia + m * (d @ d * np.eye(3) - np.outer(d, d))
    release_inertial_frame(model, body)
    values, axes = np.linalg.eigh(inertia)
    if np.linalg.det(axes) < 0:  # a proper rotation for the quaternion
        axes[:, 0] *= -1
    model.body_mass[body] = m1
    model.body_ipos[body] = c1
    model.body_inertia[body] = np.maximum(values, 1e-12)
    model.body_iquat[body] = Rotation.from_matrix(axes).as_quat(scalar_first=True)


def release_inertial_frame(model: mujoco.MjModel, body: int) -> None:
    """Let ``body``'s centre of mass and inertial axes be edited: a body compiled with its
    inertial frame on its own frame is flagged so, and MuJoCo then ignores a changed
    ``body_ipos`` (a COM shift silently did nothing) and ``mj_setConst`` refuses the model."""
    model.body_sameframe[body] = 0
    model.body_simple[body] = 0


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


def actuator_torque(model: mujoco.MjModel, tr: Trajectory, cols: np.ndarray, ctrl: np.ndarray, enabled: np.ndarray,
                    qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """(k, len(cols)) torque the joint actuators apply to each target joint at the given
    states: the affine actuator law (gain x ctrl + bias), clamped to its force range, minus the
    actuator's passive damping (a motor's back-EMF where the drive clips its voltage), zero where
    the actuator is off. This is the torque the gear train transmits."""
    out = np.zeros((len(ctrl), len(cols)))
    for i, (c, acts) in enumerate(zip(cols, joint_actuators(tr, cols))):
        for a in acts:
            gear = model.actuator_gear[a, 0]
            force = (model.actuator_gainprm[a, 0] * ctrl[:, a] + model.actuator_biasprm[a, 0]
                     + model.actuator_biasprm[a, 1] * gear * qpos[:, c] + model.actuator_biasprm[a, 2] * gear * qvel[:, c])
            if model.actuator_forcelimited[a]:
                force = np.clip(force, *model.actuator_forcerange[a])
            force -= model.actuator_damping[a] * gear * qvel[:, c]  # passive damping, outside the clamp
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


def external_torque(model: mujoco.MjModel, tr: Trajectory, cols: np.ndarray, qpos: np.ndarray,
                    qvel: np.ndarray, data: mujoco.MjData | None = None) -> np.ndarray:
    """(k, len(cols)) torque that gravity and the motion's velocity products put on each target
    joint at the given states (minus MuJoCo's bias force; joints outside the log at their
    ``qpos0``, at rest): the load the gear train holds against, contact forces aside. ``data``:
    scratch data of ``model`` whose unlogged joints are at ``qpos0`` and at rest (made if not given)."""
    data = mujoco.MjData(model) if data is None else data
    bias = np.empty(model.nv)
    dofs = tr.dadr[cols]
    out = np.empty((len(qpos), len(cols)))
    for i, (q, v) in enumerate(zip(qpos, qvel)):
        data.qpos[tr.qadr], data.qvel[tr.dadr] = q, v
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        mujoco.mj_comVel(model, data)
        mujoco.mj_rne(model, data, 0, bias)
        out[i] = -bias[dofs]
    return out


class GearboxFriction(Effect):
    """BAM's directional, Stribeck load-dependent gear friction (its M4/M5 models): dry
    friction ``|motor x tau_m - external x tau_e| x (1 + rest x exp(-(v / velocity)^2))``,
    with ``tau_m`` the actuator torque and ``tau_e`` the torque gravity and the motion put on
    the joint (:func:`external_torque`). A gear mesh rubs in proportion to the torque it
    carries, with one coefficient when the motor drives the load and another when the load
    drives it (gear efficiency differs by direction), and it sticks harder at rest.
    ``external = rest = 0`` is :class:`LoadFriction`, hence the same family."""

    name, family, refines = "gearbox_friction", "load_friction", "load_friction"
    state_friction, per_joint_allowed, focus_allowed = True, False, True

    def __init__(self, joints: tuple[str, ...] | None = None, per_joint: bool = False) -> None:
        super().__init__(joints, per_joint)
        # Replays ask for the friction one sample at a time; making MjData costs more than the step.
        self._scratch: tuple[mujoco.MjModel, mujoco.MjData] | None = None

    def _data(self, model: mujoco.MjModel) -> mujoco.MjData:
        if self._scratch is None or self._scratch[0] is not model:
            self._scratch = (model, mujoco.MjData(model))
        return self._scratch[1]

    def params(self, tr: Trajectory) -> list[Param]:
        vs = float(speed_scale(tr)[self.columns(tr)].max())
        return [Param("motor", 0.0, 0.0, 0.95, 0.005, "N·m per N·m"),
                Param("external", 0.0, 0.0, 0.95, 0.005, "N·m per N·m"),
                Param("rest", 0.0, 0.0, 4.0, 0.02, ""),
                Param("velocity", 0.2 * vs, 0.02 * vs, 2 * vs, 0.005 * vs, "rad/s")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        vs = float(speed_scale(tr)[self.columns(tr)].max())
        return [np.array([m, e, r, 0.2 * vs]) for m, e in ((0.1, 0.05), (0.3, 0.15)) for r in (0.0, 1.0)]

    def nested_starts(self, simple: np.ndarray, tr: Trajectory) -> list[np.ndarray]:
        """From load friction's ``mu``: all of it on the motor side, or part of it moved to the
        load side and to rest."""
        vs = float(speed_scale(tr)[self.columns(tr)].max())
        mu = float(simple[0])
        return [np.array([mu, 0.0, 0.0, 0.2 * vs]), np.array([0.7 * mu, 0.3 * mu, 1.0, 0.2 * vs])]

    def friction(self, x: np.ndarray, tr: Trajectory, model: mujoco.MjModel, ctrl: np.ndarray, enabled: np.ndarray,
                 qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        cols = self.columns(tr)
        carried = np.abs(x[0] * actuator_torque(model, tr, cols, ctrl, enabled, qpos, qvel)
                         - x[1] * external_torque(model, tr, cols, qpos, qvel, self._data(model)))
        out = np.zeros(qpos.shape)
        out[:, cols] = carried * (1.0 + x[2] * np.exp(-(qvel[:, cols] / x[3]) ** 2))
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
