"""The bundled models the gap tool is checked on, composed or adapted with MjSpec.

* a single Dynamixel XL330 servo swinging a pendulum (the real ``bam_xl330`` logs);
* the Unitree Go2 with its base fixed in the air (the real ``go2_fixed_base`` log);
* the crisp humanoid with its pelvis fixed above a floor, legs touching it (blind bench);
* a 6-DoF arm whose drives span two orders of magnitude (blind bench);
* a two-joint leg on a vertical rail that stands, squats and stamps on a floor (blind bench).

All use MuJoCo position actuators, so that ``ctrl`` is the commanded joint angle and the
PD loop runs inside the integrator, as it does on the servo's or the robot's own board.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from crisp_gym.humanoid import ROOT_JOINT, HumanoidConfig, add_position_servo, build_humanoid_spec

# XL330 electrical model: the firmware turns kp units and a position error into a PWM duty
# cycle, duty * vin drives a DC motor (torque kt*i, back-EMF kt*w, resistance R). The duty
# per radian and per kp unit follows from the 4096-count encoder, the kp divisor the
# firmware applies (256, measured on this servo class) and the 885-count PWM scale.
XL330_ENCODER_COUNTS = 4096
XL330_KP_DIVISOR = 256.0
XL330_PWM_SCALE = 885.0
SERVO_JOINT = "servo"
SERVO_ACTUATOR = "servo"


@dataclass(frozen=True)
class ServoConfig:
    """Parameters of the servo-pendulum model.

    Attributes:
        mass: pendulum mass (kg), a point mass at ``length`` below the axis.
        length: lever (m).
        kp: the Dynamixel's firmware position gain (its own units).
        vin: supply voltage (V).
        kt: motor torque constant after the gearbox (N·m/A), also the back-EMF constant.
        resistance: winding resistance (ohm).
        armature: reflected rotor inertia (kg·m²).
        timestep: physics step (s); the replay subdivides the log period to match it.
    Defaults are the electrical constants published for this servo class by the BAM
    actuator study (Duclusaud et al., 2025); friction is deliberately absent: it is what
    the gap tool is asked to find.
    """

    mass: float = 0.49
    length: float = 0.1
    kp: float = 400.0
    vin: float = 7.4
    kt: float = 0.346
    resistance: float = 2.50
    armature: float = 0.00157
    timestep: float = 0.0025

    @property
    def duty_per_rad(self) -> float:
        return self.kp * XL330_ENCODER_COUNTS / (2 * np.pi) / (XL330_KP_DIVISOR * XL330_PWM_SCALE)

    @property
    def stiffness(self) -> float:
        """PD stiffness in N·m/rad: torque per radian of error below saturation."""
        return self.kt / self.resistance * self.vin * self.duty_per_rad

    @property
    def back_emf_damping(self) -> float:
        return self.kt**2 / self.resistance

    @property
    def torque_limit(self) -> float:
        """Stall torque at full duty cycle."""
        return self.kt / self.resistance * self.vin


def build_servo_pendulum_spec(config: ServoConfig | None = None) -> mujoco.MjSpec:
    """One hinge (angle 0 = hanging down), a point mass, a position servo named ``servo``."""
    cfg = config or ServoConfig()
    spec = mujoco.MjSpec()
    spec.modelname = "servo_pendulum"
    spec.option.timestep = cfg.timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    body = spec.worldbody.add_body(name="pendulum")
    body.add_joint(name=SERVO_JOINT, type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 1, 0], armature=cfg.armature)
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.02, 0, 0], pos=[0, 0, -cfg.length], mass=cfg.mass,
                  contype=0, conaffinity=0)
    # The firmware clips the PWM duty cycle, i.e. the voltage: the back-EMF still brakes a servo
    # at full duty, so its damping acts outside the torque clamp.
    add_position_servo(spec, SERVO_JOINT, cfg.stiffness, cfg.back_emf_damping, cfg.torque_limit, name=SERVO_ACTUATOR,
                       passive_damping=True)
    return spec


def build_servo_pendulum(config: ServoConfig | None = None) -> mujoco.MjModel:
    return build_servo_pendulum_spec(config).compile()


GO2_JOINTS: tuple[str, ...] = tuple(f"{leg}_{part}_joint" for leg in ("FL", "FR", "RL", "RR")
                                    for part in ("hip", "thigh", "calf"))
GO2_KP = 20.0
GO2_KD = 1.5


def load_go2_fixed_base_spec(xml: str | Path, kp: float = GO2_KP, kd: float = GO2_KD) -> mujoco.MjSpec:
    """The Go2 MJCF with the free joint removed (base welded where it is) and its torque
    motors turned into PD position actuators with the gains the log was recorded with;
    torque limits stay the motors' ctrlrange."""
    xml = Path(xml)
    if not xml.is_file():
        raise FileNotFoundError(f"Go2 model not found: {xml}")
    spec = mujoco.MjSpec.from_file(str(xml))
    for body in spec.bodies:
        for joint in list(body.joints):
            if joint.type == mujoco.mjtJoint.mjJNT_FREE:
                spec.delete(joint)
                # Welded to the world, the base would collide with its own children: MuJoCo
                # filters parent-child contacts only for bodies that can move.
                for child in body.bodies:
                    spec.add_exclude(bodyname1=body.name, bodyname2=child.name)
    for key in list(spec.keys):  # keyframes are sized for the floating base
        spec.delete(key)
    model = spec.compile()  # resolves default classes, so the motors' limits are readable
    for i, act in enumerate(spec.actuators):
        limit = float(np.max(np.abs(model.actuator_ctrlrange[i])))
        act.set_to_position(kp=kp, kv=kd)
        act.ctrllimited = False
        act.forcelimited = True
        act.forcerange = (-limit, limit)
    return spec


def load_go2_fixed_base(xml: str | Path, kp: float = GO2_KP, kd: float = GO2_KD) -> mujoco.MjModel:
    return load_go2_fixed_base_spec(xml, kp, kd).compile()


HUMANOID_BENCH_JOINTS: tuple[str, ...] = tuple(f"{side}_{part}_{axis}" for side in ("L", "R")
                                                for part in ("Hip", "Knee", "Ankle", "Toe") for axis in "xyz")
"""Every leg joint: with the pelvis welded the legs' state is then complete, so replay
windows start from the whole state (an unlogged joint would restart at zero in every
window, a gap no effect explains)."""
FLOOR_GEOM = "floor"


def build_humanoid_bench_spec(penetration: float = 0.005) -> mujoco.MjSpec:
    """The humanoid with its pelvis welded in place and a floor whose top is
    ``penetration`` above the lowest foot point at rest, so that the feet touch it.

    A fixed pelvis keeps the contact cases (ground friction, softness, height, a missing
    box) while making every replay window well posed without the root state. The model
    carries the parked placeholder of the ``support_box`` effect (:func:`add_support_slot`).
    Its servos damp inside their torque clamp, as a robot's drives do.
    """
    spec = build_humanoid_spec(HumanoidConfig(arena_memory=2 * 1024 * 1024, passive_damping=False))
    spec.delete(spec.joint(ROOT_JOINT))
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    colliding = [g for g in range(model.ngeom) if model.geom_contype[g] or model.geom_conaffinity[g]]
    low = min(lowest_point(model, data, g) for g in colliding)
    top = low + penetration
    spec.worldbody.add_geom(name=FLOOR_GEOM, type=mujoco.mjtGeom.mjGEOM_BOX, size=[2.0, 2.0, 0.05],
                            pos=[0, 0, top - 0.05], contype=1, conaffinity=2, friction=[1.0, 0.005, 0.0001])
    return add_support_slot(spec)


def lowest_point(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> float:
    """Lowest world z of a sphere/capsule/box geom (others: centre minus bounding radius)."""
    size = model.geom_size[g]
    pos = data.geom_xpos[g]
    mat = data.geom_xmat[g].reshape(3, 3)
    kind = model.geom_type[g]
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return pos[2] - size[0]
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return pos[2] - abs(mat[2, 2]) * size[1] - size[0]
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        return pos[2] - float(np.abs(mat[2, :]) @ size)
    return pos[2] - model.geom_rbound[g]


def build_humanoid_bench() -> mujoco.MjModel:
    return build_humanoid_bench_spec().compile()


@dataclass(frozen=True)
class ArmDrive:
    """One joint of the bench arm: its axis, the link it moves, and its drive (gear ratio,
    rotor inertia, PD gains at the joint, torque limit)."""

    axis: tuple[float, float, float]
    link: float
    mass: float
    gear: float
    kp: float
    kd: float
    torque_limit: float


ARM_ROTOR_INERTIA = 2e-5
"""kg·m², a small BLDC rotor; each joint's armature is this times its gear ratio squared."""
ARM_DRIVES: tuple[ArmDrive, ...] = (
    ArmDrive((0, 0, 1), 0.10, 2.0, 100.0, 400.0, 20.0, 120.0),  # base yaw
    ArmDrive((0, 1, 0), 0.35, 2.5, 100.0, 400.0, 20.0, 120.0),  # shoulder pitch
    ArmDrive((0, 1, 0), 0.30, 1.5, 50.0, 150.0, 6.0, 50.0),  # elbow pitch
    ArmDrive((1, 0, 0), 0.06, 0.5, 10.0, 12.0, 0.4, 6.0),  # wrist roll
    ArmDrive((0, 1, 0), 0.06, 0.4, 5.0, 6.0, 0.15, 3.0),  # wrist pitch
    ArmDrive((1, 0, 0), 0.08, 0.2, 1.0, 1.0, 0.02, 0.6),  # flange roll
)
"""Gear ratios from 100 to 1 (reflected inertia from 0.2 to 2e-5 kg·m²), gains and torque
limits spanning more than two orders of magnitude, as on an industrial arm's big and small axes."""
ARM_JOINTS: tuple[str, ...] = tuple(f"arm{i + 1}" for i in range(len(ARM_DRIVES)))


def build_arm_spec(timestep: float = 0.001) -> mujoco.MjSpec:
    """A 6-DoF serial arm (yaw, pitch, pitch, roll, pitch, roll) on a fixed base, each link a
    capsule along x of the previous one, position servos named as their joints."""
    spec = mujoco.MjSpec()
    spec.modelname = "bench_arm"
    spec.option.timestep = timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    parent, pos = spec.worldbody, [0.0, 0.0, 0.2]
    for name, d in zip(ARM_JOINTS, ARM_DRIVES):
        body = parent.add_body(name=f"link{name[3:]}", pos=pos)
        body.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=list(d.axis),
                       armature=ARM_ROTOR_INERTIA * d.gear**2)
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, d.link, 0, 0], size=[0.03, 0, 0],
                      mass=d.mass, contype=0, conaffinity=0)
        add_position_servo(spec, name, d.kp, d.kd, d.torque_limit)
        parent, pos = body, [d.link, 0.0, 0.0]
    return spec


def build_arm() -> mujoco.MjModel:
    return build_arm_spec().compile()


RAIL_LEG_JOINTS: tuple[str, ...] = ("rail", "hip", "knee")
"""The rail leg's logged joints: the trunk's height on its rail (unactuated, a linear
encoder) and the two driven hinges."""
RAIL_LEG_ACTUATORS: tuple[str, ...] = ("hip", "knee")


def build_rail_leg_spec(timestep: float = 0.001) -> mujoco.MjSpec:
    """A 4 kg trunk on a vertical rail (a slide joint with an end stop 20 cm below its start)
    and one leg of two 24 cm links with a round foot above a floor, hip and knee position
    servos. Crouched deep enough, the trunk rests on the stop and the foot swings free;
    otherwise the leg carries the trunk: contact in stance and swing, impacts when it stamps.
    Carries the ``support_box`` placeholder (:func:`add_support_slot`)."""
    spec = mujoco.MjSpec()
    spec.modelname = "bench_rail_leg"
    spec.option.timestep = timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.worldbody.add_geom(name=FLOOR_GEOM, type=mujoco.mjtGeom.mjGEOM_BOX, size=[1.0, 1.0, 0.05], pos=[0, 0, -0.05],
                            contype=1, conaffinity=2, friction=[1.0, 0.005, 0.0001])
    trunk = spec.worldbody.add_body(name="trunk", pos=[0.0, 0.0, 0.5])
    trunk.add_joint(name="rail", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1], range=[-0.2, 0.1], limited=True,
                    damping=1.0)
    trunk.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.08, 0.08, 0.05], mass=4.0, contype=0, conaffinity=0)
    thigh = trunk.add_body(name="thigh")
    thigh.add_joint(name="hip", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 1, 0], armature=0.01)
    thigh.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, 0, 0, -0.24], size=[0.025, 0, 0], mass=1.2,
                   contype=0, conaffinity=0)
    shank = thigh.add_body(name="shank", pos=[0.0, 0.0, -0.24])
    shank.add_joint(name="knee", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 1, 0], armature=0.01)
    shank.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, 0, 0, -0.24], size=[0.02, 0, 0], mass=0.5,
                   contype=0, conaffinity=0)
    shank.add_geom(name="foot", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.03, 0, 0], pos=[0, 0, -0.24], mass=0.1,
                   contype=2, conaffinity=1, friction=[1.0, 0.005, 0.0001])
    for name in RAIL_LEG_ACTUATORS:
        add_position_servo(spec, name, kp=150.0, kv=3.0, torque_limit=40.0)
    return add_support_slot(spec)


def build_rail_leg() -> mujoco.MjModel:
    return build_rail_leg_spec().compile()


SUPPORT_SLOT = "support_slot"
"""Name of the parked placeholder box the ``support_box`` effect moves into place."""


def add_support_slot(spec: mujoco.MjSpec, half_size: tuple[float, float, float] = (0.2, 0.1, 0.1)) -> mujoco.MjSpec:
    """Add the placeholder for a missing support: a box of ``half_size`` (m; the default,
    40 x 20 cm, is a step or plank under a whole humanoid foot) on a static body of its own, parked far below the scene and colliding with nothing, so that the
    nominal model is unchanged. A compiled model cannot gain geoms; the ``support_box``
    effect moves this body (its geoms' bounding volumes move with it, which a geom of the
    world body's would not) and switches the box on instead. Returns ``spec``."""
    if any(g.name == SUPPORT_SLOT for g in spec.geoms):
        return spec
    body = spec.worldbody.add_body(name=SUPPORT_SLOT, pos=[0.0, 0.0, -100.0])
    body.add_geom(name=SUPPORT_SLOT, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half_size), contype=0, conaffinity=0,
                  rgba=[0.8, 0.5, 0.2, 1.0])
    return spec
