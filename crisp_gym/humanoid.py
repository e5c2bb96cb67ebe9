"""The SMPL-topology humanoid, composed in code with :class:`mujoco.MjSpec`.

24 bodies in MuJoCo's depth-first order (:data:`BODY_NAMES`), a free root and three
hinges (``x``, ``y``, ``z``, applied in that order, i.e. intrinsic XYZ Euler angles)
per non-root body: 69 actuated degrees of freedom, named ``"<Body>_<axis>"``
(:data:`DOF_NAMES`).

Frame: z up, the body faces +x, its left is +y. The rest pose is SMPL's T-pose (arms
along ±y), so a zero SMPL pose and zero hinge angles are the same posture.

Segment lengths are fractions of stature from Drillis & Contini (1966), as tabulated in
Winter, *Biomechanics and Motor Control of Human Movement* (4th ed., Fig. 4.1); segment
masses are fractions of body mass from de Leva (1996, J. Biomech. 29(9)); joint ranges
follow the AAOS range-of-motion tables, widened by 10-20 degrees because motion capture
and HMR output routinely exceed clinical active ranges. None of it comes from SMPL model
files. A user whose HMR produced 24 rest joint positions can pass them instead
(:func:`build_humanoid_spec` ``rest_joints``).

Actuators are MuJoCo position servos (PD inside the integrator), with the group gains of
the SMPL trackers in the field (:data:`GAIN_GROUPS`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from crisp_gym.atomic import write_text
from crisp_gym.bundled import HUMANOID_XML

BODY_NAMES: tuple[str, ...] = (
    "Pelvis", "L_Hip", "L_Knee", "L_Ankle", "L_Toe", "R_Hip", "R_Knee", "R_Ankle", "R_Toe",
    "Torso", "Spine", "Chest", "Neck", "Head", "L_Thorax", "L_Shoulder", "L_Elbow", "L_Wrist",
    "L_Hand", "R_Thorax", "R_Shoulder", "R_Elbow", "R_Wrist", "R_Hand",
)  # fmt: skip
"""The 24 body names in MuJoCo's depth-first order (the order of ``motion.npz`` ``body_names``)."""

PARENTS: dict[str, str | None] = {
    "Pelvis": None, "L_Hip": "Pelvis", "L_Knee": "L_Hip", "L_Ankle": "L_Knee", "L_Toe": "L_Ankle",
    "R_Hip": "Pelvis", "R_Knee": "R_Hip", "R_Ankle": "R_Knee", "R_Toe": "R_Ankle",
    "Torso": "Pelvis", "Spine": "Torso", "Chest": "Spine", "Neck": "Chest", "Head": "Neck",
    "L_Thorax": "Chest", "L_Shoulder": "L_Thorax", "L_Elbow": "L_Shoulder", "L_Wrist": "L_Elbow",
    "L_Hand": "L_Wrist", "R_Thorax": "Chest", "R_Shoulder": "R_Thorax", "R_Elbow": "R_Shoulder",
    "R_Wrist": "R_Elbow", "R_Hand": "R_Wrist",
}  # fmt: skip

HINGE_AXES: tuple[str, ...] = ("x", "y", "z")
DOF_NAMES: tuple[str, ...] = tuple(f"{b}_{a}" for b in BODY_NAMES[1:] for a in HINGE_AXES)
"""The 69 hinge names in qpos order (the order of ``motion.npz`` ``dof_names``)."""

ROOT_JOINT = "root"
FEET: tuple[str, ...] = ("L_Ankle", "L_Toe", "R_Ankle", "R_Toe")

# Rest (T-pose) offsets of each joint from its parent's joint, as fractions of stature.
# Heights from Drillis & Contini: hip 0.530, knee 0.285, ankle 0.039, shoulder 0.818,
# shoulder width 0.259, upper arm 0.186, forearm 0.146, hand 0.108, foot length 0.152.
_REST_OFFSETS: dict[str, tuple[float, float, float]] = {
    "Pelvis": (0.0, 0.0, 0.575),
    "L_Hip": (0.0, 0.052, -0.045), "L_Knee": (0.0, 0.0, -0.245),
    "L_Ankle": (0.0, 0.0, -0.246), "L_Toe": (0.080, 0.0, -0.026),
    "Torso": (-0.005, 0.0, 0.065), "Spine": (0.0, 0.0, 0.080), "Chest": (0.005, 0.0, 0.035),
    "Neck": (-0.010, 0.0, 0.090), "Head": (0.010, 0.0, 0.040),
    "L_Thorax": (-0.005, 0.045, 0.040), "L_Shoulder": (-0.005, 0.0845, 0.008),
    "L_Elbow": (0.0, 0.186, 0.0), "L_Wrist": (0.0, 0.146, 0.0), "L_Hand": (0.0, 0.050, 0.0),
}  # fmt: skip

# de Leva (1996) mass fractions; trunk (0.4346) and head+neck (0.0694) split over our bodies.
MASS_FRACTIONS: dict[str, float] = {
    "Pelvis": 0.1117, "Torso": 0.0800, "Spine": 0.0800, "Chest": 0.1229,
    "Neck": 0.0144, "Head": 0.0550, "L_Thorax": 0.0200,
    "L_Hip": 0.1416, "L_Knee": 0.0433, "L_Ankle": 0.0107, "L_Toe": 0.0030,
    "L_Shoulder": 0.0271, "L_Elbow": 0.0162, "L_Wrist": 0.0045, "L_Hand": 0.0016,
}  # fmt: skip

# Ranges in degrees per hinge for the left side; the right side mirrors x and z. Legs and spine
# (segments along z): x ab/adduction or lateral bend, y flexion (negative y swings the thigh
# forward, positive y bends the knee), z twist. Arms (segments along y in the T-pose): x raises
# or lowers the arm (−90° hangs it at the side), y twists it, z swings it forward (negative,
# also the elbow's flexion).
_RANGES_DEG: dict[str, tuple[tuple[float, float], ...]] = {
    "Hip": ((-40, 60), (-140, 40), (-60, 60)),
    "Knee": ((-15, 15), (-10, 160), (-30, 30)),
    "Ankle": ((-40, 40), (-55, 70), (-40, 40)),
    "Toe": ((-20, 20), (-50, 70), (-20, 20)),
    "Torso": ((-45, 45), (-60, 45), (-45, 45)),
    "Spine": ((-45, 45), (-60, 45), (-45, 45)),
    "Chest": ((-45, 45), (-60, 45), (-45, 45)),
    "Neck": ((-60, 60), (-70, 70), (-80, 80)),
    "Head": ((-50, 50), (-60, 60), (-60, 60)),
    "Thorax": ((-30, 30), (-30, 30), (-30, 30)),
    "Shoulder": ((-140, 140), (-120, 120), (-150, 90)),
    "Elbow": ((-30, 30), (-90, 90), (-165, 10)),
    "Wrist": ((-90, 90), (-60, 60), (-90, 90)),
    "Hand": ((-50, 50), (-90, 90), (-50, 50)),
}  # fmt: skip


@dataclass(frozen=True)
class GainGroup:
    """PD gains and torque limit of one group of joints."""

    kp: float
    kd: float
    torque_limit: float


GAIN_GROUPS: dict[str, GainGroup] = {
    "legs": GainGroup(800.0, 80.0, 600.0),
    "spine": GainGroup(1000.0, 100.0, 600.0),
    "arms": GainGroup(500.0, 50.0, 300.0),
    "hands": GainGroup(300.0, 30.0, 100.0),
}
"""Group gains (N·m/rad, N·m·s/rad) as used by the SMPL trackers in the field; torque
limits in N·m of the order of human peak joint torques."""

_GROUP_OF: dict[str, str] = {
    "Hip": "legs", "Knee": "legs", "Ankle": "legs", "Toe": "legs",
    "Torso": "spine", "Spine": "spine", "Chest": "spine",
    "Neck": "arms", "Head": "arms", "Thorax": "arms", "Shoulder": "arms", "Elbow": "arms",
    "Wrist": "hands", "Hand": "hands",
}  # fmt: skip

# Collision bits: the humanoid collides with the scene but not with itself (see scene.py).
HUMANOID_CONTYPE = 2
HUMANOID_CONAFFINITY = 1


def _kind(body: str) -> str:
    """'L_Knee' -> 'Knee', 'Torso' -> 'Torso'."""
    return body.split("_", 1)[1] if body[:2] in ("L_", "R_") else body


def _mirror(name: str) -> str:
    """Left-side table key for a body on either side."""
    return "L_" + name[2:] if name.startswith("R_") else name


def gain_group(body: str) -> GainGroup:
    """The :class:`GainGroup` of a non-root body."""
    return GAIN_GROUPS[_GROUP_OF[_kind(body)]]


def joint_range_deg(body: str) -> np.ndarray:
    """(3, 2) hinge ranges in degrees for ``body``; right-side x and z ranges are mirrored."""
    ranges = np.array(_RANGES_DEG[_kind(body)], dtype=float)
    if body.startswith("R_"):
        ranges[[0, 2]] = -ranges[[0, 2], ::-1]
    return ranges


def hinge_ranges() -> np.ndarray:
    """(69, 2) hinge ranges in radians, in :data:`DOF_NAMES` order."""
    return np.deg2rad(np.concatenate([joint_range_deg(b) for b in BODY_NAMES[1:]]))


def default_rest_joints(height: float = 1.70) -> np.ndarray:
    """(24, 3) world positions of the joints in the T-pose for a person of ``height`` metres.

    Feet on z = 0 (the lowest point of the sole), facing +x.
    """
    if not 0.5 <= height <= 2.5:
        raise ValueError(f"height must be a human stature in metres (0.5-2.5), got {height}")
    offsets = {}
    for body in BODY_NAMES:
        x, y, z = _REST_OFFSETS[_mirror(body)]
        offsets[body] = np.array([x, -y if body.startswith("R_") else y, z]) * height
    joints = np.zeros((len(BODY_NAMES), 3))
    for i, body in enumerate(BODY_NAMES):
        parent = PARENTS[body]
        base = np.zeros(3) if parent is None else joints[BODY_NAMES.index(parent)]
        joints[i] = base + offsets[body]
    return joints


@dataclass(frozen=True)
class HumanoidConfig:
    """Parameters of :func:`build_humanoid_spec`.

    Attributes:
        height: stature in metres; scales every segment of the anthropometric table.
        mass: body mass in kg; ``None`` scales 70 kg at 1.70 m with height cubed.
        rest_joints: optional (24, 3) T-pose joint positions (z up, facing +x, body order
            :data:`BODY_NAMES`), e.g. from the user's HMR; overrides ``height`` for lengths.
        timestep: physics step in seconds (the paper simulates at 120 Hz).
        armature: rotor inertia added to every hinge (kg·m²); keeps stiff PD stable.
        passive_damping: each servo's damping ``kd`` acts as passive damping at its hinge
            (MuJoCo's actuator ``damping``), outside the torque clamp: the torque is
            ``clip(kp (target − q), ±limit) − kd q̇``. MuJoCo integrates passive damping
            implicitly always, but a clamped actuator's own damping only while the actuator is
            below its limit: a saturated servo on a light body (a hand, a toe; 1e-4 kg·m²) then
            turns explicitly at 120 Hz and whips round at hundreds of rad/s. ``False``: the damping
            inside the clamp, ``clip(kp (target − q) − kd q̇, ±limit)``, as a drive's controller
            computes it (the sim-to-real benchmark's robot models).
        friction: sliding, torsional and rolling friction of the body geoms.
        arena_memory: MuJoCo arena bytes per simulation (MJCF `<size memory>`); the default would be ~18 MB.
    """

    height: float = 1.70
    mass: float | None = None
    rest_joints: np.ndarray | None = field(default=None, compare=False)
    timestep: float = 1.0 / 120.0
    armature: float = 0.02
    passive_damping: bool = True
    friction: tuple[float, float, float] = (1.0, 0.005, 0.0001)
    arena_memory: int = 6 * 1024 * 1024

    def body_mass(self) -> float:
        return self.mass if self.mass is not None else 70.0 * (self.height / 1.70) ** 3


def _capsule_radius(body: str, height: float) -> float:
    """Segment radius as a fraction of stature (girths from the same anthropometric sources)."""
    radii = {
        "Pelvis": 0.055, "Torso": 0.058, "Spine": 0.060, "Chest": 0.062, "Neck": 0.030,
        "Thorax": 0.030, "Hip": 0.036, "Knee": 0.027, "Shoulder": 0.024, "Elbow": 0.020,
        "Wrist": 0.016, "Hand": 0.012,
    }  # fmt: skip
    return radii[_kind(body)] * height


def _add_segment_geoms(body_spec: mujoco.MjsBody, body: str, joint: np.ndarray,
                       child_joints: list[np.ndarray], rest: np.ndarray, height: float,
                       mass: float, cfg: HumanoidConfig) -> None:
    """Add the collision geoms of one segment, in the body's frame (origin at its joint)."""
    common = dict(
        contype=HUMANOID_CONTYPE, conaffinity=HUMANOID_CONAFFINITY, friction=cfg.friction,
        mass=mass, rgba=(0.85, 0.6, 0.45, 1.0) if body != "Head" else (0.9, 0.7, 0.55, 1.0),
    )
    kind = _kind(body)
    sole_z = -joint[2]  # the floor in this body's frame, for the feet
    if kind == "Ankle":
        toe = child_joints[0] - joint
        heel_x, front_x = -0.045 * height, toe[0]
        top_z = 0.045 * height + sole_z
        body_spec.add_geom(
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=((heel_x + front_x) / 2, 0.0, (sole_z + top_z) / 2),
            size=((front_x - heel_x) / 2, 0.030 * height, (top_z - sole_z) / 2), **common)
    elif kind == "Toe":
        length = 0.045 * height
        top_z = 0.020 * height + sole_z
        body_spec.add_geom(
            type=mujoco.mjtGeom.mjGEOM_BOX, pos=(length / 2, 0.0, (sole_z + top_z) / 2),
            size=(length / 2, 0.030 * height, (top_z - sole_z) / 2), **common)
    elif kind == "Head":
        r = 0.060 * height
        body_spec.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=(0.01 * height, 0, 0.045 * height),
                           size=(r, 0, 0), **common)
    elif kind == "Hand":
        direction = np.sign(joint[1] - rest[BODY_NAMES.index(PARENTS[body])][1])
        length = 0.06 * height
        body_spec.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, pos=(0, direction * length / 2, 0),
                           size=(0.012 * height, length / 2, 0.022 * height), **common)
    elif kind == "Pelvis":
        hips = [c - joint for c in child_joints[:2]]
        r = _capsule_radius(body, height)
        body_spec.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                           fromto=(*hips[0] * [1, 0.6, 0] + [0, 0, 0.02 * height],
                                   *hips[1] * [1, 0.6, 0] + [0, 0, 0.02 * height]),
                           size=(r, 0, 0), **common)
    else:
        # A capsule from the joint towards the mean of the child joints.
        end = np.mean(child_joints, axis=0) - joint
        r = _capsule_radius(body, height)
        length = np.linalg.norm(end)
        start = end / length * min(r, 0.3 * length) if kind in ("Chest", "Spine", "Torso") else 0 * end
        stop = end - end / length * min(r, 0.3 * length) if kind in ("Chest", "Thorax") else end
        body_spec.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=(*start, *stop),
                           size=(r, 0, 0), **common)


def build_humanoid_spec(config: HumanoidConfig | None = None) -> mujoco.MjSpec:
    """Compose the humanoid as an :class:`mujoco.MjSpec` (no scene, no floor).

    The model has one free joint (:data:`ROOT_JOINT`), 69 hinges with ranges, 69 position
    actuators named like their hinges, ``integrator="implicitfast"`` at ``config.timestep``.
    """
    cfg = config or HumanoidConfig()
    if cfg.rest_joints is not None:
        rest = np.asarray(cfg.rest_joints, dtype=float)
        if rest.shape != (len(BODY_NAMES), 3) or not np.all(np.isfinite(rest)):
            raise ValueError(f"rest_joints must be finite with shape (24, 3), got {rest.shape}")
        # Stature from the ankle-to-head span, in the proportions of the default table.
        unit = default_rest_joints(1.0)
        span = lambda j: j[BODY_NAMES.index("Head"), 2] - j[[3, 7], 2].mean()  # noqa: E731
        height = float(span(rest) / span(unit))
        rest = rest - [0.0, 0.0, rest[[3, 7], 2].mean() - unit[3, 2] * height]
    else:
        rest = default_rest_joints(cfg.height)
        height = cfg.height
    mass = cfg.body_mass()

    spec = mujoco.MjSpec()
    spec.modelname = "crisp_humanoid"
    spec.memory = cfg.arena_memory
    spec.option.timestep = cfg.timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.compiler.degree = False

    children: dict[str, list[str]] = {b: [] for b in BODY_NAMES}
    for b in BODY_NAMES[1:]:
        children[PARENTS[b]].append(b)

    bodies: dict[str, mujoco.MjsBody] = {}
    for i, body in enumerate(BODY_NAMES):
        parent = PARENTS[body]
        parent_spec = spec.worldbody if parent is None else bodies[parent]
        parent_pos = np.zeros(3) if parent is None else rest[BODY_NAMES.index(parent)]
        b = parent_spec.add_body(name=body, pos=rest[i] - parent_pos)
        bodies[body] = b
        if parent is None:
            b.add_freejoint(name=ROOT_JOINT)
        else:
            ranges = np.deg2rad(joint_range_deg(body))
            for axis_index, axis in enumerate(HINGE_AXES):
                b.add_joint(name=f"{body}_{axis}", type=mujoco.mjtJoint.mjJNT_HINGE,
                            axis=np.eye(3)[axis_index], range=ranges[axis_index], limited=True,
                            armature=cfg.armature)
        child_joints = [rest[BODY_NAMES.index(c)] for c in children[body]]
        if not child_joints:  # toes, head, hands end the chains
            child_joints = [rest[i] + (rest[i] - parent_pos) * 0.5]
        _add_segment_geoms(b, body, rest[i], child_joints, rest, height,
                           MASS_FRACTIONS[_mirror(body)] * mass, cfg)

    for body in BODY_NAMES[1:]:
        group = gain_group(body)
        for axis in HINGE_AXES:
            add_position_servo(spec, f"{body}_{axis}", group.kp, group.kd, group.torque_limit,
                               passive_damping=cfg.passive_damping)
    return spec


def add_position_servo(spec: mujoco.MjSpec, joint: str, kp: float, kv: float, torque_limit: float,
                       name: str | None = None, passive_damping: bool = False) -> mujoco.MjsActuator:
    """A PD position actuator on ``joint`` (named ``name``, default the joint's name): ``ctrl``
    is the target angle, unbounded, and the torque is clamped to ±``torque_limit``; with
    ``passive_damping`` the damping ``kv`` is the actuator's passive damping, outside the clamp
    (see :class:`HumanoidConfig`)."""
    act = spec.add_actuator(name=name or joint, target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
    act.set_to_position(kp=kp, kv=0.0 if passive_damping else kv)
    if passive_damping:
        act.damping = [kv, 0.0, 0.0]
    act.forcelimited = True
    act.forcerange = (-torque_limit, torque_limit)
    act.ctrllimited = False
    return act


def servo_damping(model: mujoco.MjModel) -> np.ndarray:
    """(nu,) damping ``kd`` of each position servo of ``model``, whether it damps inside its
    clamped force (``kv``) or passively (see :func:`add_position_servo`)."""
    return model.actuator_damping - model.actuator_biasprm[:, 2]


def build_humanoid(config: HumanoidConfig | None = None) -> mujoco.MjModel:
    """Compile :func:`build_humanoid_spec`."""
    return build_humanoid_spec(config).compile()


DEFAULT_MODEL_PATH = HUMANOID_XML


def write_default_model(path: Path = DEFAULT_MODEL_PATH) -> Path:
    """Write the default humanoid's MJCF (the file shipped in ``assets/humanoid``)."""
    return write_text(path, build_humanoid_spec().to_xml())
