"""Reconstruction quality against the ground truth: Chamfer distances, support coverage,
non-penetration of the reference human, primitive count.

A reconstruction is a list of :class:`~crisp_gym.scene.Box` (planar and contact primitives) or a
triangle mesh (the TSDF baselines); the ground truth is a list of boxes. Every distance is exact:
points are sampled uniformly by area on one surface and their Euclidean distance to the other
surface's triangles is computed by Open3D (``RaycastingScene.compute_distance``).

Which surface a set of boxes has:

* the ground truth's is the boundary of the union of its boxes (a stair block's faces against
  the floor or against the next block are inside the solid and are not surface);
* a reconstruction's is, by default (``recon_faces="surface"``), the +z face of each box: the
  surface that planar fitting and contact completion put where the points or contacts were (both
  build boxes as ``[u, v, normal]`` with the box *behind* that face, and a box with the identity
  rotation, like the floor, has its top there). The 0.05 m back and side faces are a device to
  make a solid for simulation, not a claim about the scene. ``recon_faces="all"`` measures the
  boundary of the union instead, like the ground truth.

The ground truth's floor is usually a 40 m slab: pass ``bounds`` to measure only the part of the
ground truth (or the reconstruction) that lies in the region of interest.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import mujoco
import numpy as np
import open3d as o3d
import trimesh

from crisp_gym.humanoid import build_humanoid
from crisp_gym.metrics import box_signed_distance
from crisp_gym.motion import Motion, humanoid_qpos_adr
from crisp_gym.reconstruct.raycast import box_mesh
from crisp_gym.scene import Box

Geometry = list[Box] | trimesh.Trimesh
"""A scene: box primitives or a triangle mesh."""

RECON_FACES = ("surface", "all")
MAX_SAMPLES = 5_000_000
"""More sample points than this means the spacing or the bounds are wrong for the scene's size."""


@dataclass(frozen=True)
class Distances:
    """One-way point-to-surface distances (m).

    Attributes:
        mean: mean distance.
        median: median distance.
        p90: 90th percentile.
        samples: number of sample points.
    """

    mean: float
    median: float
    p90: float
    samples: int


@dataclass(frozen=True)
class NonPenetration:
    """PLACE-style non-penetration of a posed body in a scene.

    Attributes:
        vertex_score: mean over frames of the fraction of body surface points not inside the scene
            (PLACE's non-collision score; 1 = no penetration).
        frame_score: fraction of frames in which no body surface point is inside the scene.
        max_depth: deepest penetration over all frames (m, >= 0).
    """

    vertex_score: float
    frame_score: float
    max_depth: float


# --------------------------------------------------------------------------- surfaces


def _check_boxes(geometry: object, what: str) -> list[Box]:
    if isinstance(geometry, Box):
        return [geometry]
    if not isinstance(geometry, (list, tuple)) or not geometry or not all(isinstance(b, Box) for b in geometry):
        raise ValueError(f"{what} must be a non-empty list of Box or a trimesh.Trimesh, got {type(geometry).__name__}")
    return list(geometry)


def surface_mesh(geometry: Geometry, faces: Literal["surface", "all"] = "all") -> trimesh.Trimesh:
    """The surface of a scene as a triangle mesh (see the module docstring for ``faces``).

    A mesh is returned as it is; boxes become the boundary of their union (``"all"``) or each
    box's +z face (``"surface"``).
    """
    if faces not in RECON_FACES:
        raise ValueError(f"faces must be one of {RECON_FACES}, got {faces!r}")
    if isinstance(geometry, trimesh.Trimesh):
        if len(geometry.faces) == 0:
            raise ValueError("the mesh has no triangles")
        return geometry
    boxes = _check_boxes(geometry, "geometry")
    if faces == "surface":
        signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)
        vertices = [b.center + b.half_size[2] * b.rotation[:, 2] + (signs * b.half_size[:2]) @ b.rotation[:, :2].T
                    for b in boxes]
        quads = np.array([[0, 1, 2], [0, 2, 3]])
        return trimesh.Trimesh(vertices=np.concatenate(vertices),
                               faces=np.concatenate([quads + 4 * i for i in range(len(boxes))]), process=False)
    meshes = [box_mesh(b) for b in boxes]
    return meshes[0] if len(meshes) == 1 else trimesh.boolean.union(meshes, engine="manifold")


def _crop(mesh: trimesh.Trimesh, bounds: np.ndarray | None) -> trimesh.Trimesh:
    """The part of ``mesh`` inside the axis-aligned ``bounds`` (2, 3)."""
    if bounds is None:
        return mesh
    for axis in range(3):
        for sign, corner in ((1.0, bounds[0]), (-1.0, bounds[1])):
            normal = np.zeros(3)
            normal[axis] = sign
            mesh = trimesh.intersections.slice_mesh_plane(mesh, normal, corner, cap=False)
            if len(mesh.faces) == 0:
                return mesh
    return mesh


def _check_bounds(bounds: np.ndarray | None) -> np.ndarray | None:
    if bounds is None:
        return None
    bounds = np.asarray(bounds, dtype=float)
    if bounds.shape != (2, 3) or not np.all(np.isfinite(bounds)) or np.any(bounds[1] <= bounds[0]):
        raise ValueError(f"bounds must be finite (2, 3) [min corner, max corner] with max > min, got {bounds.tolist()}")
    return bounds


def sample_surface(mesh: trimesh.Trimesh, spacing: float, bounds: np.ndarray | None = None,
                   seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points uniformly distributed by area on ``mesh`` (within ``bounds``), about one per
    ``spacing``², with the normals of their triangles. Returns (N, 3) points, (N, 3) normals."""
    if not spacing > 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    mesh = _crop(mesh, _check_bounds(bounds))
    if len(mesh.faces) == 0 or mesh.area <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    count = max(1, int(np.ceil(mesh.area / spacing**2)))
    if count > MAX_SAMPLES:
        raise ValueError(f"{mesh.area:.1f} m² at spacing {spacing} m needs {count} points (max {MAX_SAMPLES}); "
                         f"pass bounds around the region of interest or a larger spacing")
    points, face = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points), np.asarray(mesh.face_normals[face])


def distance_to(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """(N,) exact distance (m) from ``points`` (N, 3) to the triangles of ``mesh``."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
    query = o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))
    return scene.compute_distance(query).numpy().astype(float)


def _summary(d: np.ndarray) -> Distances:
    if d.size == 0:
        raise ValueError("no sample points: the surface is empty (inside the bounds)")
    return Distances(mean=float(d.mean()), median=float(np.median(d)), p90=float(np.percentile(d, 90)),
                     samples=int(d.size))


# --------------------------------------------------------------------------- metrics


def chamfer_recon_to_gt(recon: Geometry, gt: list[Box], spacing: float = 0.02, bounds: np.ndarray | None = None,
                        recon_faces: Literal["surface", "all"] = "surface", seed: int = 0) -> Distances:
    """One-way Chamfer Recon→GT (precision): distances from points on the reconstruction's surface
    (within ``bounds``) to the ground-truth surface."""
    points, _ = sample_surface(surface_mesh(recon, recon_faces), spacing, bounds, seed)
    return _summary(distance_to(points, surface_mesh(_check_boxes(gt, "gt"))))


def chamfer_gt_to_recon(recon: Geometry, gt: list[Box], spacing: float = 0.02, bounds: np.ndarray | None = None,
                        recon_faces: Literal["surface", "all"] = "surface", seed: int = 0) -> Distances:
    """One-way Chamfer GT→Recon (completeness): distances from points on the ground-truth surface
    (within ``bounds``) to the reconstruction's surface."""
    points, _ = sample_surface(surface_mesh(_check_boxes(gt, "gt")), spacing, bounds, seed)
    return _summary(distance_to(points, surface_mesh(recon, recon_faces)))


def chamfer_two_way(recon: Geometry, gt: list[Box], spacing: float = 0.02, bounds: np.ndarray | None = None,
                    recon_faces: Literal["surface", "all"] = "surface", seed: int = 0) -> float:
    """Symmetric Chamfer distance (m): the mean of the two one-way mean distances."""
    forward = chamfer_recon_to_gt(recon, gt, spacing, bounds, recon_faces, seed)
    backward = chamfer_gt_to_recon(recon, gt, spacing, bounds, recon_faces, seed)
    return 0.5 * (forward.mean + backward.mean)


def support_coverage(recon: Geometry, gt: list[Box], distance: float = 0.03, min_up_cos: float = 0.9,
                     spacing: float = 0.02, bounds: np.ndarray | None = None,
                     recon_faces: Literal["surface", "all"] = "surface", seed: int = 0) -> float:
    """Fraction of the ground truth's upward-facing surface area (normal z >= ``min_up_cos``;
    within ``bounds``) that lies within ``distance`` of the reconstruction's surface."""
    if not distance > 0 or not -1.0 <= min_up_cos <= 1.0:
        raise ValueError(f"distance must be positive and min_up_cos in [-1, 1], got {distance}, {min_up_cos}")
    points, normals = sample_surface(surface_mesh(_check_boxes(gt, "gt")), spacing, bounds, seed)
    up = points[normals[:, 2] >= min_up_cos]
    if len(up) == 0:
        raise ValueError("the ground truth has no upward-facing surface (within the bounds)")
    return float(np.mean(distance_to(up, surface_mesh(recon, recon_faces)) <= distance))


def primitive_count(recon: Geometry) -> int:
    """Number of primitives: boxes for a box scene, triangles for a mesh."""
    if isinstance(recon, trimesh.Trimesh):
        return len(recon.faces)
    return len(_check_boxes(recon, "recon"))


# --------------------------------------------------------------------------- non-penetration


def _geom_surface(model: mujoco.MjModel, geom: int, spacing: float, rng: np.random.Generator) -> np.ndarray:
    """(P, 3) points uniformly by area on a sphere, capsule or box geom, in the geom's frame."""
    kind, size = model.geom_type[geom], model.geom_size[geom]
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        mesh = trimesh.creation.box(extents=2 * size)
    elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=size[0])
    elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        mesh = trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[24, 24])
    else:
        raise ValueError(f"humanoid geom {geom} has type {kind}; expected box, sphere or capsule")
    count = max(8, int(np.ceil(mesh.area / spacing**2)))
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=rng)
    return np.asarray(points)


def _signed_distance(scene: Geometry) -> Callable[[np.ndarray], np.ndarray]:
    """A function: (N, 3) points → (N,) signed distance to the scene's solids (negative inside)."""
    if isinstance(scene, trimesh.Trimesh):
        if not scene.is_watertight:
            raise ValueError("non-penetration needs a closed (watertight) mesh to tell inside from outside")
        raycast = o3d.t.geometry.RaycastingScene()
        raycast.add_triangles(o3d.core.Tensor(np.asarray(scene.vertices, dtype=np.float32)),
                              o3d.core.Tensor(np.asarray(scene.faces, dtype=np.uint32)))
        return lambda points: raycast.compute_signed_distance(
            o3d.core.Tensor(points.astype(np.float32))).numpy().astype(float)
    boxes = _check_boxes(scene, "scene")
    return lambda points: box_signed_distance(points, boxes)


def non_penetration(scene: Geometry, motion: Motion, model: mujoco.MjModel | None = None,
                    spacing: float = 0.03, tolerance: float = 0.005, seed: int = 0) -> NonPenetration:
    """How much of the posed humanoid stays outside the scene over a motion (PLACE's score).

    Points are sampled on every humanoid geom (about one per ``spacing``²) and posed by forward
    kinematics in each frame; a point is inside when its signed distance to the scene is below
    ``-tolerance`` (a sole resting on a surface is not penetrating it).

    Args:
        scene: boxes, or a closed mesh.
        motion: the reference motion, in the scene's frame.
        model: the humanoid (default: :func:`crisp_gym.humanoid.build_humanoid`).
        spacing: sample spacing on the body (m).
        tolerance: penetration depth below which a point still counts as outside (m).
        seed: seeds the body samples.
    """
    if not isinstance(motion, Motion):
        raise ValueError(f"motion must be a crisp_gym.motion.Motion, got {type(motion).__name__}")
    if not spacing > 0 or not tolerance >= 0:
        raise ValueError(f"spacing must be positive and tolerance >= 0, got {spacing}, {tolerance}")
    signed_distance = _signed_distance(scene)
    model = model or build_humanoid()
    data = mujoco.MjData(model)
    rng = np.random.default_rng(seed)
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] != 0]
    local = [_geom_surface(model, g, spacing, rng) for g in geoms]
    adr = humanoid_qpos_adr(model)
    qpos = motion.qpos()
    outside = np.empty(len(qpos))
    depth = np.empty(len(qpos))
    for k, q in enumerate(qpos):
        data.qpos[adr:adr + q.shape[0]] = q
        mujoco.mj_kinematics(model, data)
        points = np.concatenate([data.geom_xpos[g] + p @ data.geom_xmat[g].reshape(3, 3).T
                                 for g, p in zip(geoms, local)])
        sdf = signed_distance(points)
        outside[k] = np.mean(sdf >= -tolerance)
        depth[k] = max(0.0, -float(sdf.min()))
    return NonPenetration(vertex_score=float(outside.mean()), frame_score=float(np.mean(outside == 1.0)),
                          max_depth=float(depth.max()))


# --------------------------------------------------------------------------- frames


def heading_alignment(recon_path: np.ndarray, gt_path: np.ndarray) -> np.ndarray:
    """(4, 4) yaw about z plus a horizontal shift taking a reconstruction's world onto the truth's.

    The pipeline fixes scale, gravity and the floor height, but the world's heading and
    horizontal origin are its free choice; fitting only those (2-D Procrustes on the pelvis
    paths, (T, 3) each, frame by frame) leaves every real error in the metrics.
    """
    recon_path, gt_path = np.asarray(recon_path, dtype=float), np.asarray(gt_path, dtype=float)
    if recon_path.shape != gt_path.shape or recon_path.ndim != 2 or recon_path.shape[1] != 3 or len(gt_path) < 2:
        raise ValueError(f"paths must be matching (T >= 2, 3) arrays, got {recon_path.shape} and {gt_path.shape}")
    a = recon_path[:, :2] - recon_path[:, :2].mean(0)
    b = gt_path[:, :2] - gt_path[:, :2].mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    flip = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = (u @ flip @ vt).T
    out = np.eye(4)
    out[:2, :2] = rotation
    out[:2, 3] = gt_path[:, :2].mean(0) - rotation @ recon_path[:, :2].mean(0)
    return out
