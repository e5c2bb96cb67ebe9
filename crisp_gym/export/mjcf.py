"""MJCF export: the scene alone, and the scene with the humanoid and its motion, for three consumers.

Profiles (:data:`PROFILES`), each written by :func:`write_mjcf` into its own folder:

* ``"mujoco"``: ``scene.xml`` (the boxes, named, with friction) and ``track.xml``, the model
  ``CrispTrack-v0`` simulates (:func:`crisp_gym.envs.tracking.build_track_spec`) with one ``<key>`` per
  motion frame (``qpos``, ``qvel``, ``ctrl`` = the hinge angles as PD targets, ``time``), plus the motion
  as a companion ``motion.npz``. Reloaded, ``track.xml`` steps identically to the env's model.
* ``"mjx"``: the same for MJX, MuJoCo Playground and Brax. The box named ``floor`` becomes a plane at its
  top face: MJX collides boxes with its general convex routine but planes analytically, and the humanoid
  only ever touches the floor's top. Checked with ``mujoco.mjx.put_model`` when MJX is installed.
* ``"dm_control"``: split as dm_control composes models: ``arena.xml`` (the scene plus the physics
  options), ``walker.xml`` (the humanoid without its free joint: ``arena.attach(walker).add("freejoint")``)
  and the combined ``track.xml``; all parse with ``dm_control.mjcf.from_path``.

MuJoCo writes numbers with 6 significant digits, which moves the 1/120 s timestep by 3e-9 s and joint
limits by up to 5e-6 rad, enough for trajectories to drift apart. :func:`exact_xml` therefore rewrites
every physics number with the compiled model's value at full precision (shortest round-trip form) and
checks that the file compiles back to the same model.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from crisp_gym.atomic import write_text
from crisp_gym.clip import Clip
from crisp_gym.envs.config import TrackConfig
from crisp_gym.envs.tracking import build_track_spec
from crisp_gym.humanoid import BODY_NAMES, ROOT_JOINT, HumanoidConfig, build_humanoid_spec
from crisp_gym.scene import Box, build_scene_spec

PROFILES = ("mujoco", "mjx", "dm_control")

# Fields a reloaded model must reproduce exactly (to 1e-12): everything the dynamics read.
_CHECKED_FIELDS = (
    "body_pos", "body_quat", "body_ipos", "body_iquat", "body_mass", "body_inertia",
    "geom_type", "geom_pos", "geom_quat", "geom_size", "geom_friction", "geom_contype", "geom_conaffinity",
    "jnt_type", "jnt_pos", "jnt_axis", "jnt_range", "dof_armature", "dof_damping", "dof_frictionloss",
    "actuator_gainprm", "actuator_biasprm", "actuator_damping", "actuator_forcerange", "actuator_ctrlrange",
    "actuator_gear",
    "key_qpos", "key_qvel", "key_ctrl", "key_time",
)  # fmt: skip


@dataclass(frozen=True)
class MjcfExportConfig:
    """What :func:`write_mjcf` writes.

    Attributes:
        keyframes: add one ``<key>`` per motion frame to ``track.xml`` (the companion ``motion.npz``
            is written either way).
        sim_hz: physics rate of the exported model (the env's, 120 Hz).
        friction: sliding, torsional and rolling friction of the scene's boxes (the env's).
    """

    keyframes: bool = True
    sim_hz: float = TrackConfig.sim_hz
    friction: tuple[float, float, float] = (1.0, 0.005, 0.0001)

    def __post_init__(self) -> None:
        if self.sim_hz <= 0:
            raise ValueError(f"sim_hz must be positive, got {self.sim_hz}")


# ------------------------------------------------------------------------------------------------
# Full-precision XML


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(values))


def _set(elem: ET.Element, attr: str, values) -> None:
    """Overwrite a numeric attribute the writer emitted, keeping its number of entries."""
    text = elem.get(attr)
    if text is None:
        return
    try:
        count = len([float(v) for v in text.split()])
    except ValueError:  # a keyword (e.g. integrator="implicitfast"), not numbers
        return
    elem.set(attr, _fmt(np.ravel(values)[:count]))


def _check_name(elem: ET.Element, expected: str, kind: str) -> None:
    name = elem.get("name")
    if name is not None and name != expected:
        raise ValueError(f"XML {kind} {name!r} does not line up with the compiled model's {expected!r}")


def _exact_bodies(root: ET.Element, model: mujoco.MjModel, spec_geoms: dict[int, mujoco.MjsGeom]) -> None:
    world = root.find("worldbody")
    bodies = [world, *world.iter("body")]  # document order is MuJoCo's body order
    if len(bodies) != model.nbody:
        raise ValueError(f"the XML has {len(bodies)} bodies, the model {model.nbody}")
    for b, elem in enumerate(bodies):
        if b:
            _check_name(elem, model.body(b).name, "body")
            _set(elem, "pos", model.body_pos[b])
            _set(elem, "quat", model.body_quat[b])
        geoms = elem.findall("geom")
        if len(geoms) != model.body_geomnum[b]:
            raise ValueError(f"body {model.body(b).name!r}: {len(geoms)} geoms in the XML, "
                             f"{model.body_geomnum[b]} in the model")
        for i, g_elem in enumerate(geoms):
            g = model.body_geomadr[b] + i
            _check_name(g_elem, model.geom(g).name, "geom")
            for attr, value in (("pos", model.geom_pos[g]), ("quat", model.geom_quat[g]),
                                ("size", model.geom_size[g]), ("friction", model.geom_friction[g]),
                                ("margin", model.geom_margin[g]), ("gap", model.geom_gap[g]),
                                ("solref", model.geom_solref[g]), ("solimp", model.geom_solimp[g]),
                                ("mass", spec_geoms[g].mass)):
                _set(g_elem, attr, value)
        joints = [e for e in elem if e.tag in ("joint", "freejoint")]
        if len(joints) != model.body_jntnum[b]:
            raise ValueError(f"body {model.body(b).name!r}: {len(joints)} joints in the XML, "
                             f"{model.body_jntnum[b]} in the model")
        for i, j_elem in enumerate(joints):
            j = model.body_jntadr[b] + i
            _check_name(j_elem, model.joint(j).name, "joint")
            dof = model.jnt_dofadr[j]
            for attr, value in (("pos", model.jnt_pos[j]), ("axis", model.jnt_axis[j]),
                                ("range", model.jnt_range[j]), ("stiffness", model.jnt_stiffness[j]),
                                ("armature", model.dof_armature[dof]), ("damping", model.dof_damping[dof]),
                                ("frictionloss", model.dof_frictionloss[dof])):
                _set(j_elem, attr, value)


def _exact_rest(root: ET.Element, model: mujoco.MjModel) -> None:
    option = root.find("option")
    if option is not None:
        for attr in list(option.attrib):
            if isinstance(getattr(model.opt, attr, None), (float, np.ndarray)):
                _set(option, attr, getattr(model.opt, attr))
    actuators = root.findall("actuator/*")
    if len(actuators) != model.nu:
        raise ValueError(f"the XML has {len(actuators)} actuators, the model {model.nu}")
    for a, elem in enumerate(actuators):
        _check_name(elem, model.actuator(a).name, "actuator")
        for attr, value in (("gainprm", model.actuator_gainprm[a]), ("biasprm", model.actuator_biasprm[a]),
                            ("dynprm", model.actuator_dynprm[a]), ("gear", model.actuator_gear[a]),
                            ("damping", model.actuator_damping[a]),
                            ("forcerange", model.actuator_forcerange[a]),
                            ("ctrlrange", model.actuator_ctrlrange[a])):
            _set(elem, attr, value)
    for k, elem in enumerate(root.findall("keyframe/key")):
        for attr, value in (("qpos", model.key_qpos[k]), ("qvel", model.key_qvel[k]),
                            ("ctrl", model.key_ctrl[k]), ("act", model.key_act[k]), ("time", model.key_time[k])):
            _set(elem, attr, value)


def _assert_same(model: mujoco.MjModel, reloaded: mujoco.MjModel) -> None:
    if model.opt.timestep != reloaded.opt.timestep:
        raise ValueError(f"timestep {reloaded.opt.timestep} differs from {model.opt.timestep}")
    for name in _CHECKED_FIELDS:
        a, b = getattr(model, name), getattr(reloaded, name)
        if a.shape != b.shape or (a.size and np.abs(a.astype(float) - b.astype(float)).max() > 1e-12):
            raise ValueError(f"the written MJCF does not reproduce the model's {name}")


def exact_xml(spec: mujoco.MjSpec) -> str:
    """``spec`` as MJCF text whose numbers reproduce its compiled model exactly.

    Raises ``ValueError`` for structures the rewrite does not follow (``<frame>`` or ``<default>``
    classes) or when the text does not compile back to the same model.
    """
    model = spec.compile()
    root = ET.fromstring(spec.to_xml())
    if root.find(".//frame") is not None or root.find("default/default") is not None:
        raise ValueError("exact_xml follows flat models only: no <frame> elements or <default> classes")
    _exact_bodies(root, model, {g.id: g for g in spec.geoms})
    _exact_rest(root, model)
    ET.indent(root)
    text = ET.tostring(root, encoding="unicode") + "\n"
    _assert_same(model, mujoco.MjModel.from_xml_string(text))
    return text


# ------------------------------------------------------------------------------------------------
# Model specs per profile


def _check_boxes(clip: Clip) -> None:
    kind = getattr(clip, "scene_kind", "boxes")
    if kind != "boxes":
        raise ValueError(f"clip {clip.name!r} has a {kind!r} scene; the exporters take box scenes only "
                         "(scene_kind 'boxes')")


def track_spec(clip: Clip, config: MjcfExportConfig = MjcfExportConfig()) -> mujoco.MjSpec:
    """The env's model of ``clip`` (humanoid + scene), with one keyframe per motion frame if asked."""
    _check_boxes(clip)
    spec = build_track_spec(clip.boxes, timestep=1.0 / config.sim_hz)
    for geom in spec.worldbody.geoms:
        geom.friction = config.friction
    if config.keyframes:
        motion = clip.motion.in_humanoid_order()
        qpos, qvel = motion.qpos(), motion.qvel()
        for k in range(motion.num_frames):
            spec.add_key(name=f"frame_{k:05d}", qpos=qpos[k], qvel=qvel[k], ctrl=motion.dof_pos[k],
                         time=k / motion.fps)
    return spec


def floor_to_plane(spec: mujoco.MjSpec) -> bool:
    """Turn the world geom named ``floor`` (an axis-aligned box) into a plane at its top face.

    MuJoCo planes collide as infinite half-spaces; the plane keeps the box's extent for rendering.
    Returns whether a floor was found.
    """
    floor = next((g for g in spec.worldbody.geoms if g.name == "floor"), None)
    if floor is None or floor.type != mujoco.mjtGeom.mjGEOM_BOX:
        return False
    if not np.allclose(np.abs(floor.quat), [1, 0, 0, 0], atol=1e-12):
        raise ValueError("the floor box is tilted; only an axis-aligned floor becomes a plane")
    half = np.array(floor.size)
    floor.type = mujoco.mjtGeom.mjGEOM_PLANE
    floor.pos = np.array(floor.pos) + [0.0, 0.0, half[2]]
    floor.size = (half[0], half[1], 0.5)  # the third entry is the rendering grid spacing
    return True


def mjx_check(model: mujoco.MjModel) -> bool:
    """Load ``model`` with ``mujoco.mjx.put_model`` (JAX backend); ``False`` when MJX is not installed.

    Raises ``ValueError`` naming the unsupported feature when MJX refuses the model.
    """
    try:
        from mujoco import mjx
    except ImportError:
        return False
    try:
        mjx.put_model(model, impl="jax")
    except NotImplementedError as err:
        raise ValueError(f"MJX does not support this model: {err}") from None
    return True


def walker_spec(config: MjcfExportConfig = MjcfExportConfig()) -> mujoco.MjSpec:
    """The humanoid for dm_control composition: no free joint, pelvis at the origin.

    ``arena.attach(walker)`` wraps the walker in an attachment body; the free joint added to it then
    carries the pelvis pose, so a motion's root position and quaternion are that joint's qpos.
    """
    spec = build_humanoid_spec(HumanoidConfig(timestep=1.0 / config.sim_hz))
    spec.delete(spec.joint(ROOT_JOINT))
    spec.body(BODY_NAMES[0]).pos = (0.0, 0.0, 0.0)
    return spec


def arena_spec(boxes: list[Box], config: MjcfExportConfig = MjcfExportConfig()) -> mujoco.MjSpec:
    """The scene for dm_control composition, carrying the physics options (they come from the root model)."""
    spec = build_scene_spec(boxes, config.friction)
    humanoid = build_humanoid_spec(HumanoidConfig(timestep=1.0 / config.sim_hz))
    spec.option.timestep = humanoid.option.timestep
    spec.option.integrator = humanoid.option.integrator
    spec.memory = humanoid.memory
    return spec


# ------------------------------------------------------------------------------------------------
# Writing


def write_scene_mjcf(boxes: list[Box], path: str | Path, friction: tuple[float, float, float] = (1.0, 0.005, 0.0001),
                     floor_as_plane: bool = False) -> Path:
    """The boxes alone as MJCF (named geoms with friction), at full precision; written atomically."""
    spec = build_scene_spec(boxes, friction)
    if floor_as_plane:
        floor_to_plane(spec)
    return write_text(path, exact_xml(spec))


def write_mjcf(clip: Clip, directory: str | Path, profile: str = "mujoco",
               config: MjcfExportConfig = MjcfExportConfig()) -> list[Path]:
    """Write ``clip`` as MJCF for ``profile`` (see the module docstring) into ``directory``; returns the files."""
    if profile not in PROFILES:
        raise ValueError(f"profile must be one of {PROFILES}, got {profile!r}")
    _check_boxes(clip)
    directory = Path(directory)
    written = []
    if profile == "dm_control":
        written.append(write_text(directory / "arena.xml", exact_xml(arena_spec(clip.boxes, config))))
        written.append(write_text(directory / "walker.xml", exact_xml(walker_spec(config))))
    else:
        written.append(write_scene_mjcf(clip.boxes, directory / "scene.xml", config.friction,
                                        floor_as_plane=profile == "mjx"))
    spec = track_spec(clip, config)
    if profile == "mjx":
        floor_to_plane(spec)
        mjx_check(spec.compile())
    written.append(write_text(directory / "track.xml", exact_xml(spec)))
    written.append(clip.motion.save(directory / "motion.npz"))  # Motion.save writes atomically
    return written
