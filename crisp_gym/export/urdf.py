"""URDF export: the scene as one fixed link of boxes, and the humanoid as a chain of revolute joints.

Scene (:func:`scene_robot`): one link, ``scene``, with a visual and a collision box per primitive,
both named like the box; import it with a fixed base.

Humanoid (:func:`humanoid_robot`): URDF joints have one degree of freedom, so a body with three
hinges becomes three revolute joints named like the hinges (``L_Knee_x``, ``L_Knee_y``, ``L_Knee_z``,
applied in that order, as MuJoCo does) through two small intermediate links (``L_Knee_x_link``,
``L_Knee_y_link``); the last joint's child is the body's own link, which carries its mass, inertia and
geometry. The pelvis is the root link; importers give it the floating base. MuJoCo's URDF parser
fixes the root to the world and, by default, fuses it away with its mass: the file carries MuJoCo's
URDF extension ``<mujoco><compiler fusestatic="false"/></mujoco>`` so the pelvis stays a body, and
``spec = mujoco.MjSpec.from_file("humanoid.urdf"); spec.body("Pelvis").add_freejoint()`` gives it
the free joint (``docs/export.md``).

Approximations (also listed in ``docs/export.md``):

* a capsule becomes a cylinder plus two spheres: the same solid, since URDF has no capsule;
* intermediate links get a small mass and inertia (:attr:`UrdfConfig.link_mass`), because importers
  reject massless links; they add ``46 × link_mass`` to the body mass;
* URDF requires a joint velocity limit and MuJoCo has none: :attr:`UrdfConfig.velocity_limit`;
* what URDF cannot hold (PD gains, armature, the position servos) goes into ``humanoid_actuators.json``;
  contact parameters and collision filtering (the humanoid does not collide with itself) are
  simulator settings.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import yourdfpy
from lxml import etree
from yourdfpy import urdf as U

from crisp_gym.atomic import atomic_path, write_text
from crisp_gym.export.actuators import actuator_table, joint_servos
from crisp_gym.export.meshes import SOURCE_RGBA
from crisp_gym.humanoid import HumanoidConfig, build_humanoid
from crisp_gym.scene import Box


@dataclass(frozen=True)
class UrdfConfig:
    """Choices URDF forces on the humanoid's export.

    Attributes:
        link_mass: mass (kg) of each intermediate link between the hinges of one body; importers
            (PhysX, Bullet) reject massless links.
        link_inertia: diagonal inertia (kg·m²) of each intermediate link.
        velocity_limit: joint velocity limit (rad/s) URDF requires; MuJoCo has none, so it is set
            above peak human joint speeds (~30 rad/s in throwing) to never bind.
    """

    link_mass: float = 1e-3
    link_inertia: float = 1e-6
    velocity_limit: float = 40.0

    def __post_init__(self) -> None:
        if self.link_mass <= 0 or self.link_inertia <= 0 or self.velocity_limit <= 0:
            raise ValueError("link_mass, link_inertia and velocity_limit must be positive")


def pose_matrix(pos, quat) -> np.ndarray:
    """4×4 homogeneous transform of a position and a w x y z quaternion."""
    transform = np.eye(4)
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, dtype=float))
    transform[:3, :3] = mat.reshape(3, 3)
    transform[:3, 3] = pos
    return transform


def scene_robot(boxes: list[Box], name: str = "crisp_scene") -> U.Robot:
    """The boxes as one link, ``scene``: a visual and a collision element per box, named like it."""
    if not boxes:
        raise ValueError("a scene needs at least one box")
    link = U.Link(name="scene")
    for i, box in enumerate(boxes):
        box_name = box.name or f"scene_{i}"
        origin = np.eye(4)
        origin[:3, :3], origin[:3, 3] = box.rotation, box.center
        geometry = U.Geometry(box=U.Box(size=2 * box.half_size))
        material = U.Material(name=box.source, color=U.Color(rgba=np.array(SOURCE_RGBA[box.source])))
        link.visuals.append(U.Visual(name=box_name, origin=origin, geometry=geometry, material=material))
        link.collisions.append(U.Collision(name=box_name, origin=origin.copy(), geometry=geometry))
    names = [c.name for c in link.collisions]
    if len(names) != len(set(names)):
        raise ValueError(f"box names must be unique, got {names}")
    return U.Robot(name=name, links=[link])


def _geometry(model: mujoco.MjModel, g: int, name: str) -> list[tuple[str, np.ndarray, U.Geometry]]:
    """URDF (name, origin, geometry) parts of MuJoCo geom ``g``; a capsule is a cylinder and two spheres."""
    kind, size = mujoco.mjtGeom(int(model.geom_type[g])), model.geom_size[g]
    origin = pose_matrix(model.geom_pos[g], model.geom_quat[g])
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        return [(name, origin, U.Geometry(box=U.Box(size=2 * size)))]
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return [(name, origin, U.Geometry(sphere=U.Sphere(radius=float(size[0]))))]
    if kind in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
        parts = [(name, origin, U.Geometry(cylinder=U.Cylinder(radius=float(size[0]), length=float(2 * size[1]))))]
        if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
            for end, sign in (("cap0", -1.0), ("cap1", 1.0)):
                cap = origin.copy()
                cap[:3, 3] += sign * size[1] * origin[:3, 2]  # along the geom's own z axis
                parts.append((f"{name}_{end}", cap, U.Geometry(sphere=U.Sphere(radius=float(size[0])))))
        return parts
    raise ValueError(f"geom {name!r} is a {kind.name}; URDF export takes boxes, spheres, "
                     "capsules and cylinders")


def _body_link(model: mujoco.MjModel, b: int) -> U.Link:
    name = model.body(b).name
    inertial = U.Inertial(origin=pose_matrix(model.body_ipos[b], model.body_iquat[b]),
                          mass=float(model.body_mass[b]), inertia=np.diag(model.body_inertia[b]))
    link = U.Link(name=name, inertial=inertial)
    for i in range(model.body_geomnum[b]):
        g = model.body_geomadr[b] + i
        rgba = model.geom_rgba[g]
        for part, origin, geometry in _geometry(model, g, model.geom(g).name or f"{name}_geom{i}"):
            material = U.Material(name=f"{part}_color", color=U.Color(rgba=np.array(rgba)))
            link.visuals.append(U.Visual(name=part, origin=origin, geometry=geometry, material=material))
            link.collisions.append(U.Collision(name=part, origin=origin.copy(), geometry=geometry))
    return link


def humanoid_robot(model: mujoco.MjModel | None = None, config: UrdfConfig = UrdfConfig(),
                   name: str = "crisp_humanoid") -> U.Robot:
    """The humanoid (default: :func:`crisp_gym.humanoid.build_humanoid`) as a URDF robot (module docstring)."""
    model = model if model is not None else build_humanoid(HumanoidConfig())
    servo = joint_servos(model)
    links, joints = [], []
    for b in range(1, model.nbody):
        body = model.body(b).name
        links.append(_body_link(model, b))
        parent_id = model.body_parentid[b]
        if parent_id == 0:
            if model.body_jntnum[b] != 1 or int(model.jnt_type[model.body_jntadr[b]]) != mujoco.mjtJoint.mjJNT_FREE:
                raise ValueError(f"root body {body!r} must have exactly one free joint")
            continue
        jnt_ids = range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])
        parent = model.body(parent_id).name
        origin = pose_matrix(model.body_pos[b], model.body_quat[b])
        if not jnt_ids:
            joints.append(U.Joint(name=f"{body}_fixed", type="fixed", parent=parent, child=body, origin=origin))
            continue
        for k, j in enumerate(jnt_ids):
            jname = model.joint(j).name
            if int(model.jnt_type[j]) != mujoco.mjtJoint.mjJNT_HINGE or np.any(model.jnt_pos[j] != 0):
                raise ValueError(f"joint {jname!r}: URDF export takes hinges at their body's origin")
            last = k == len(jnt_ids) - 1
            child = body if last else f"{jname}_link"
            if not last:
                links.append(U.Link(name=child, inertial=U.Inertial(
                    origin=np.eye(4), mass=config.link_mass, inertia=np.eye(3) * config.link_inertia)))
            a = servo.get(j)
            effort = float(model.actuator_forcerange[a, 1]) if a is not None and model.actuator_forcelimited[a] else None
            lower, upper = (float(v) for v in model.jnt_range[j]) if model.jnt_limited[j] else (None, None)
            dof = model.jnt_dofadr[j]
            joints.append(U.Joint(
                name=jname, type="revolute" if model.jnt_limited[j] else "continuous", parent=parent, child=child,
                origin=origin if k == 0 else np.eye(4), axis=model.jnt_axis[j].copy(),
                limit=U.Limit(effort=effort, velocity=config.velocity_limit, lower=lower, upper=upper),
                dynamics=U.Dynamics(damping=float(model.dof_damping[dof]),
                                    friction=float(model.dof_frictionloss[dof]))))
            parent = child
    return U.Robot(name=name, links=links, joints=joints)


def write_robot(robot: U.Robot, path: str | Path, mujoco_compiler: dict[str, str] | None = None) -> Path:
    """Write a URDF robot atomically (yourdfpy's writer), with MuJoCo's URDF extension
    ``<mujoco><compiler .../></mujoco>`` when ``mujoco_compiler`` gives its attributes (other
    URDF readers skip the element)."""
    tree = yourdfpy.URDF(robot=robot, build_scene_graph=False, load_meshes=False).write_xml()
    if mujoco_compiler:
        extension = etree.Element("mujoco")
        etree.SubElement(extension, "compiler", mujoco_compiler)
        tree.getroot().insert(0, extension)
    with atomic_path(path) as tmp:
        tree.write(str(tmp), xml_declaration=True, pretty_print=True)
    return Path(path)


def write_urdf(boxes: list[Box], directory: str | Path, config: UrdfConfig = UrdfConfig()) -> list[Path]:
    """``scene.urdf``, ``humanoid.urdf`` and ``humanoid_actuators.json`` into ``directory``."""
    directory = Path(directory)
    model = build_humanoid(HumanoidConfig())
    return [
        write_robot(scene_robot(boxes), directory / "scene.urdf"),
        # MuJoCo fuses a URDF's root link into the world, dropping the pelvis (7.8 kg) with it
        write_robot(humanoid_robot(model, config), directory / "humanoid.urdf", {"fusestatic": "false"}),
        write_text(directory / "humanoid_actuators.json", json.dumps(actuator_table(model), indent=1) + "\n"),
    ]
