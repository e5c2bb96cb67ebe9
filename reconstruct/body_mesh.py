"""The humanoid as one triangle mesh, posed per frame by MuJoCo's forward kinematics.

The synthetic videos render the person with it, and the alignment renders the motion's humanoid
into the camera to measure the metric scale, so both see exactly the same body: the collision
geoms of :func:`crisp_gym.humanoid.build_humanoid` (capsules, boxes and a sphere).

Each geom becomes a small closed mesh in its own frame once; posing a frame is then a single
batched rotation of all vertices by their geom's world pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np
import open3d as o3d
import trimesh

from crisp_gym.geometry import pixel_rays
from crisp_gym.humanoid import HumanoidConfig, build_humanoid
from crisp_gym.motion import humanoid_body_ids, humanoid_qpos_adr


def _geom_template(geom_type: int, size: np.ndarray) -> trimesh.Trimesh:
    """A closed mesh of one MuJoCo geom in its own frame (capsules along local z)."""
    if geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return trimesh.creation.capsule(height=2.0 * size[1], radius=size[0], count=[10, 6])
    if geom_type == mujoco.mjtGeom.mjGEOM_BOX:
        return trimesh.creation.box(extents=2.0 * size)
    if geom_type == mujoco.mjtGeom.mjGEOM_SPHERE:
        return trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    raise ValueError(f"the humanoid has a geom of type {geom_type}; only capsules, boxes and spheres are meshed")




def cast_mesh(vertices: np.ndarray, faces: np.ndarray, intrinsic: np.ndarray, cam_c2w: np.ndarray,
              width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast one world-frame mesh into a pinhole camera, casting only the rays of its image box.

    Returns z-depth (H, W) float32 (0 = missed), world-frame unit normals (H, W, 3) float32 and
    the hit triangle (H, W) int64 (-1 = missed).
    """
    depth = np.zeros((height, width), np.float32)
    normals = np.zeros((height, width, 3), np.float32)
    triangle = np.full((height, width), -1, np.int64)
    rot, eye = cam_c2w[:3, :3], cam_c2w[:3, 3]
    cam = (vertices - eye) @ rot
    if cam[:, 2].max() <= 1e-6:
        return depth, normals, triangle  # entirely behind the camera
    if cam[:, 2].min() > 1e-6:  # all in front: only the projected bounding box can be hit
        uv = cam[:, :2] / cam[:, 2:3] * intrinsic[[0, 1], [0, 1]] + intrinsic[:2, 2]
        u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int), 0)
        u1, v1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 1, [width, height])
        if u0 >= u1 or v0 >= v1:
            return depth, normals, triangle
    else:  # straddles the image plane: its projection is unbounded
        u0, v0, u1, v1 = 0, 0, width, height
    dirs = pixel_rays(intrinsic, u1, v1, u0, v0) @ rot.T  # camera z = 1: t_hit is z-depth
    rays = np.concatenate([np.broadcast_to(eye, dirs.shape), dirs], axis=-1).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)), o3d.core.Tensor(np.asarray(faces, np.uint32)))
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = hit["t_hit"].numpy()
    ok = np.isfinite(t_hit)
    depth[v0:v1, u0:u1] = np.where(ok, t_hit, 0.0)
    normals[v0:v1, u0:u1] = np.where(ok[..., None], hit["primitive_normals"].numpy(), 0.0)
    triangle[v0:v1, u0:u1] = np.where(ok, hit["primitive_ids"].numpy().astype(np.int64), -1)
    return depth, normals, triangle


@dataclass
class BodyMesher:
    """Poses the humanoid's collision geoms as one triangle mesh.

    Attributes:
        model: the humanoid (default: :func:`build_humanoid` of ``HumanoidConfig()``); the
            posed qpos must be this model's (free root + 69 hinges).
    """

    model: mujoco.MjModel = field(default_factory=lambda: build_humanoid(HumanoidConfig()))

    def __post_init__(self) -> None:
        body_index = {int(b): i for i, b in enumerate(humanoid_body_ids(self.model))}
        local, faces, geom_of_vertex, body_of_vertex, body_of_face = [], [], [], [], []
        offset = 0
        self._geoms = np.array([g for g in range(self.model.ngeom)
                                if int(self.model.geom_bodyid[g]) in body_index])
        for k, g in enumerate(self._geoms):
            mesh = _geom_template(int(self.model.geom_type[g]), self.model.geom_size[g])
            local.append(mesh.vertices)
            faces.append(mesh.faces + offset)
            body = body_index[int(self.model.geom_bodyid[g])]
            geom_of_vertex.append(np.full(len(mesh.vertices), k))
            body_of_vertex.append(np.full(len(mesh.vertices), body))
            body_of_face.append(np.full(len(mesh.faces), body))
            offset += len(mesh.vertices)
        self._local = np.concatenate(local)
        self._geom_of_vertex = np.concatenate(geom_of_vertex)
        self.faces: np.ndarray = np.concatenate(faces).astype(np.int64)
        """(F, 3) triangles, shared by every pose."""
        self.body_of_face: np.ndarray = np.concatenate(body_of_face)
        """(F,) index into :data:`BODY_NAMES` of the body each triangle belongs to."""
        self.body_of_vertex: np.ndarray = np.concatenate(body_of_vertex)
        """(V,) index into :data:`BODY_NAMES` of the body each vertex belongs to."""
        self._data = mujoco.MjData(self.model)
        self._adr = humanoid_qpos_adr(self.model)

    @property
    def num_vertices(self) -> int:
        return len(self._local)

    def pose(self, qpos: np.ndarray) -> np.ndarray:
        """(V, 3) vertices of the humanoid at one qpos (76,) in qpos's frame."""
        qpos = np.asarray(qpos, dtype=np.float64)
        self._data.qpos[self._adr:self._adr + qpos.shape[0]] = qpos
        mujoco.mj_kinematics(self.model, self._data)
        pos = self._data.geom_xpos[self._geoms]
        mat = self._data.geom_xmat[self._geoms].reshape(-1, 3, 3)
        g = self._geom_of_vertex
        return np.einsum("vij,vj->vi", mat[g], self._local) + pos[g]

    def trimesh(self, qpos: np.ndarray) -> trimesh.Trimesh:
        """The posed humanoid as a :class:`trimesh.Trimesh` (e.g. to export or inspect)."""
        return trimesh.Trimesh(self.pose(qpos), self.faces, process=False)
