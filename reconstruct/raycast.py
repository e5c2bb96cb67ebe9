"""Headless depth rendering of triangle meshes with Open3D's ``RaycastingScene``.

The synthetic videos, the tests and the benchmarks all render through this, so a depth image
means the same thing everywhere: z-depth along the optical axis (OpenCV camera), 0 where a ray
hits nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import trimesh

from crisp_gym.geometry import pixel_rays
from crisp_gym.scene import Box


def box_mesh(box: Box) -> trimesh.Trimesh:
    """A box primitive as a closed 12-triangle mesh in world coordinates."""
    mesh = trimesh.creation.box(extents=2.0 * np.asarray(box.half_size))
    transform = np.eye(4)
    transform[:3, :3] = box.rotation
    transform[:3, 3] = box.center
    mesh.apply_transform(transform)
    return mesh






@dataclass
class DepthRenderer:
    """Ray-casts depth and per-pixel mesh ids for a fixed set of static meshes plus per-frame extras.

    ``static`` meshes (the scene) are added once; ``render`` takes optional ``dynamic`` meshes
    (e.g. the posed humanoid of one frame) that are added for that call only.
    """

    static: list[trimesh.Trimesh]

    def __post_init__(self) -> None:
        if not self.static:
            raise ValueError("DepthRenderer needs at least one static mesh")
        self._static_geometry = [self._to_o3d(m) for m in self.static]

    @staticmethod
    def _to_o3d(mesh: trimesh.Trimesh) -> o3d.t.geometry.TriangleMesh:
        return o3d.t.geometry.TriangleMesh(
            o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.int32)),
        )

    def render(self, intrinsic: np.ndarray, cam_c2w: np.ndarray, width: int, height: int,
               dynamic: list[trimesh.Trimesh] = ()) -> tuple[np.ndarray, np.ndarray]:
        """Depth (H, W) float32 and the id (H, W) int of the mesh each pixel sees (-1 = none).

        Ids number ``static`` first, then ``dynamic``, in order.
        """
        scene = o3d.t.geometry.RaycastingScene()
        for geometry in self._static_geometry:
            scene.add_triangles(geometry)
        for mesh in dynamic:
            scene.add_triangles(self._to_o3d(mesh))
        # Our own rays rather than ``create_rays_pinhole``, which puts pixel centres at u + 0.5:
        # OpenCV (and ``Frames.rays``) put them at integer u, v.
        dirs = pixel_rays(intrinsic, width, height) @ cam_c2w[:3, :3].T  # camera z-component 1, so t_hit is the z-depth
        origins = np.broadcast_to(cam_c2w[:3, 3], dirs.shape)
        rays = o3d.core.Tensor(np.concatenate([origins, dirs], axis=-1).astype(np.float32))
        hit = scene.cast_rays(rays)
        t_hit = hit["t_hit"].numpy()
        ids = hit["geometry_ids"].numpy().astype(np.int64)
        missed = ~np.isfinite(t_hit)
        ids[missed] = -1
        depth = np.where(missed, 0.0, t_hit).astype(np.float32)
        return depth, ids
