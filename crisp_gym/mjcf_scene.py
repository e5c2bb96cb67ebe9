"""Scenes that are not boxes: a clip's ``scene.xml`` geometry (heightfields, meshes) in other models.

Box clips are composed from their primitives (:func:`crisp_gym.scene.add_boxes`). A clip whose
``scene_kind`` is another (:data:`crisp_gym.clip.SCENE_KINDS`, e.g. the TSDF baselines of
``crisp_gym.reconstruct.baselines``) brings its geometry in ``scene.xml`` and the files it references;
:func:`attach_scene` copies it into a model spec (with the scene's collision bits), and
:func:`scene_surface` gives its surface as triangles, to sample scene-aware observations from.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import trimesh

from crisp_gym.scene import SCENE_CONAFFINITY, SCENE_CONTYPE

SURFACE_GEOMS = (mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_HFIELD)


def load_scene_spec(scene_xml: str | Path) -> mujoco.MjSpec:
    """``scene_xml`` as a spec whose geoms carry the scene's collision bits.

    The scene must be static: joints would shift the humanoid's qpos layout.
    """
    path = Path(scene_xml)
    if not path.is_file():
        raise FileNotFoundError(f"no scene file at {path}")
    spec = mujoco.MjSpec.from_file(str(path))  # keeps the file's folder, so relative mesh paths resolve
    if spec.joints:
        raise ValueError(f"{path} has joints {[j.name for j in spec.joints]}; a scene must be static geometry")
    for geom in spec.geoms:
        geom.contype, geom.conaffinity = SCENE_CONTYPE, SCENE_CONAFFINITY
    return spec


def attach_scene(spec: mujoco.MjSpec, scene_xml: str | Path, prefix: str = "scene/",
                 offset: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0)) -> None:
    """Copy the geometry of ``scene_xml`` (geoms, meshes, heightfields) into ``spec``'s world,
    shifted by ``offset``."""
    spec.attach(load_scene_spec(scene_xml), prefix=prefix, frame=spec.worldbody.add_frame(pos=offset))


def _hfield_mesh(model: mujoco.MjModel, hfield: int) -> tuple[np.ndarray, np.ndarray]:
    """Top surface of a heightfield in its geom's frame: (V, 3) vertices, (F, 3) faces."""
    nrow, ncol = model.hfield_nrow[hfield], model.hfield_ncol[hfield]
    sx, sy, sz, _ = model.hfield_size[hfield]
    adr = model.hfield_adr[hfield]
    z = model.hfield_data[adr:adr + nrow * ncol].reshape(nrow, ncol) * sz
    x, y = np.meshgrid(np.linspace(-sx, sx, ncol), np.linspace(-sy, sy, nrow))  # row 0 at -y
    idx = np.arange(nrow * ncol).reshape(nrow, ncol)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return np.stack([x, y, z], -1).reshape(-1, 3), faces


def scene_surface(scene_xml: str | Path) -> trimesh.Trimesh:
    """The world-body geoms of ``scene_xml`` (boxes, meshes, heightfields) as one world-frame mesh.

    Meshes give their own triangles (what was reconstructed), not the convex hull MuJoCo
    collides; heightfields give their top surface.
    """
    path = Path(scene_xml)
    if not path.is_file():
        raise FileNotFoundError(f"no scene file at {path}")
    model = mujoco.MjModel.from_xml_path(str(path))
    parts = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != 0:
            continue
        kind = mujoco.mjtGeom(model.geom_type[g])
        if kind not in SURFACE_GEOMS:
            raise ValueError(f"{path}: geom {model.geom(g).name or g} has type {kind.name}; "
                             f"scene surfaces support {[t.name for t in SURFACE_GEOMS]}")
        if kind == mujoco.mjtGeom.mjGEOM_BOX:
            box = trimesh.creation.box(extents=2 * model.geom_size[g])
            vertices, faces = box.vertices, box.faces
        elif kind == mujoco.mjtGeom.mjGEOM_MESH:
            m = model.geom_dataid[g]
            v0, nv, f0, nf = model.mesh_vertadr[m], model.mesh_vertnum[m], model.mesh_faceadr[m], model.mesh_facenum[m]
            vertices, faces = model.mesh_vert[v0:v0 + nv], model.mesh_face[f0:f0 + nf]
        else:
            vertices, faces = _hfield_mesh(model, model.geom_dataid[g])
        rotation = np.empty(9)
        mujoco.mju_quat2Mat(rotation, model.geom_quat[g])
        parts.append(trimesh.Trimesh(vertices @ rotation.reshape(3, 3).T + model.geom_pos[g], faces, process=False))
    if not parts:
        raise ValueError(f"{path} has no scene geometry in its world body")
    return trimesh.util.concatenate(parts)


def surface_points(surface: trimesh.Trimesh, spacing: float, seed: int = 0) -> np.ndarray:
    """(P, 3) points spread uniformly by area over ``surface``, about one per ``spacing``²."""
    if spacing <= 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    count = max(1, int(np.ceil(surface.area / spacing**2)))
    points, _ = trimesh.sample.sample_surface(surface, count, seed=seed)
    return points

