"""Mesh export of a scene for viewers and mesh-based simulators: GLB and OBJ via trimesh.

Each box is one named node. In GLB the node holds a shared cube with corners at ±1 and the box's
pose and half sizes in its transform (stored as JSON doubles), so no size is rounded to float32;
OBJ has no node transforms and gets the corners themselves, with ``digits`` decimals, one object
and one material per box (``scene.mtl`` beside it), so OBJ readers load one geometry per box.

Colours: uniform grey by default; ``color_by_source=True`` colours the primitives by where they
came from (planar fits blue, contact-derived orange), the overlay the paper's figures use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from crisp_gym.atomic import atomic_path, write_text
from crisp_gym.scene import Box

SOURCE_RGBA = {"planar": (0.45, 0.6, 0.85, 1.0), "contact": (0.9, 0.55, 0.3, 1.0)}
"""Colours of the primitives by source (those of the MJCF scene)."""
UNIFORM_RGBA = (0.7, 0.7, 0.7, 1.0)
MESH_FORMATS = ("glb", "obj")


def box_transform(box: Box) -> np.ndarray:
    """4×4 transform taking the cube with corners at ±1 onto ``box``."""
    transform = np.eye(4)
    transform[:3, :3] = box.rotation * box.half_size  # scales the columns: the box axes
    transform[:3, 3] = box.center
    return transform


def scene_mesh(boxes: list[Box], color_by_source: bool = False) -> trimesh.Scene:
    """The boxes as a trimesh scene: one node per box, named like it (``scene_<i>`` when unnamed)."""
    if not boxes:
        raise ValueError("a scene needs at least one box")
    scene = trimesh.Scene()
    cubes: dict[str, trimesh.Trimesh] = {}
    for i, box in enumerate(boxes):
        key = box.source if color_by_source else "uniform"
        if key not in cubes:
            cube = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
            rgba = SOURCE_RGBA[key] if color_by_source else UNIFORM_RGBA
            cube.visual.face_colors = np.round(np.array(rgba) * 255).astype(np.uint8)
            cubes[key] = cube
        name = box.name or f"scene_{i}"
        if name in scene.graph.nodes:
            raise ValueError(f"box names must be unique, {name!r} appears twice")
        scene.add_geometry(cubes[key], node_name=name, geom_name=f"cube_{key}", transform=box_transform(box))
    return scene


def write_scene_mesh(boxes: list[Box], path: str | Path, color_by_source: bool = False, digits: int = 10) -> Path:
    """Write the scene as ``.glb`` or ``.obj`` (by the suffix of ``path``), atomically.

    ``digits``: decimals of the OBJ vertex coordinates.
    """
    path = Path(path)
    kind = path.suffix.lower().lstrip(".")
    if kind not in MESH_FORMATS:
        raise ValueError(f"mesh files must end in one of {['.' + f for f in MESH_FORMATS]}, got {path.name!r}")
    scene = scene_mesh(boxes, color_by_source)
    with atomic_path(path) as tmp:
        if kind == "glb":
            scene.export(tmp, file_type="glb")
        else:
            obj, mtl = _obj_and_mtl(scene, path.with_suffix(".mtl").name, digits)
            tmp.write_text(obj)
    if kind == "obj":
        write_text(path.with_suffix(".mtl"), mtl)
    return path


def _obj_and_mtl(scene: trimesh.Scene, mtl_name: str, digits: int) -> tuple[str, str]:
    """OBJ and MTL text: one object and one material per box, both named like it, corners in world
    coordinates. trimesh's own OBJ writer shares one material among boxes of one colour, and
    readers that split a file by material (trimesh's default) then merged them into one mesh."""
    obj, mtl, first = ["# crisp-gym scene: one object and one material per box", f"mtllib {mtl_name}"], [], 1
    for name in scene.graph.nodes_geometry:
        transform, geometry = scene.graph[name]
        mesh = scene.geometry[geometry]
        corners = trimesh.transform_points(mesh.vertices, transform)
        red, green, blue, alpha = mesh.visual.face_colors[0] / 255.0
        mtl += [f"newmtl {name}", f"Kd {red:.4f} {green:.4f} {blue:.4f}", f"d {alpha:.4f}", ""]
        obj += [f"o {name}", f"usemtl {name}"]
        obj += [f"v {x:.{digits}f} {y:.{digits}f} {z:.{digits}f}" for x, y, z in corners]
        obj += [f"f {a} {b} {c}" for a, b, c in mesh.faces + first]
        first += len(corners)
    return "\n".join(obj) + "\n", "\n".join(mtl)
