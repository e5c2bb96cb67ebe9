"""Stage 3, per group: RANSAC normals snapped to gravity, the scene's dominant yaw, and coplanar
planes that touch merged into one surface."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from crisp_gym.geometry import plane_axes, ransac_plane, snap_to_gravity
from crisp_gym.reconstruct.planes.config import PlaneFitConfig

_Z = np.array([0.0, 0.0, 1.0])


def _snap(normal: np.ndarray, cfg: PlaneFitConfig) -> np.ndarray:
    """Exactly vertical / horizontal when within ``snap_deg`` of it (gravity-aligned input)."""
    return snap_to_gravity(normal / np.linalg.norm(normal), cfg.snap_deg)


def ransac_normal(points: np.ndarray, prior: np.ndarray, cfg: PlaneFitConfig,
                   rng: np.random.Generator) -> np.ndarray:
    """Normal (towards ``prior``) of the RANSAC plane with the most inliers among hypotheses within
    the normal tolerance of ``prior``, refined by least squares on its inliers and snapped."""
    sample = points[rng.integers(0, len(points), cfg.ransac_sample)] if len(points) > cfg.ransac_sample else points
    found = ransac_plane(sample, prior, cfg.min_normal_cosine, cfg.ransac_distance, cfg.ransac_iterations, rng,
                         refinements=1)
    return _snap(prior if found is None else found[0], cfg)  # none: too few points to disagree with the prior


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value below and above which half the weight lies."""
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


@dataclass
class Plane:
    """A fitted plane: ``normal · p = offset`` for its inlier ``points``."""

    normal: np.ndarray
    offset: float
    points: np.ndarray  # (N, 3) inliers
    frames: int
    groups: list[int]


def footprint_cells(uv: np.ndarray, cell: float) -> np.ndarray:
    return np.floor(uv / cell).astype(np.int64)


def _thin(points: np.ndarray, cell: float) -> np.ndarray:
    """One point per occupied ``cell``-sized voxel (footprint comparisons need no more)."""
    voxels = np.floor(points / cell).astype(np.int64)
    voxels -= voxels.min(axis=0)
    span = voxels.max(axis=0) + 1
    _, first = np.unique((voxels[:, 0] * span[1] + voxels[:, 1]) * span[2] + voxels[:, 2], return_index=True)
    return points[first]


def _touching(a: np.ndarray, b: np.ndarray, normal: np.ndarray, cell: float) -> bool:
    """Whether the footprints of point sets ``a`` and ``b`` on the plane of ``normal`` come within
    one ``cell`` of each other."""
    basis = plane_axes(normal)
    ca, cb = footprint_cells(a @ basis.T, cell), footprint_cells(b @ basis.T, cell)
    low = np.minimum(ca.min(axis=0), cb.min(axis=0)) - 1
    ca, cb = ca - low, cb - low
    width = max(ca[:, 1].max(), cb[:, 1].max()) + 2
    shifts = np.array([i * width + j for i in (-1, 0, 1) for j in (-1, 0, 1)])
    grown = (ca[:, 0] * width + ca[:, 1])[:, None] + shifts[None]
    return bool(np.intersect1d(grown.ravel(), cb[:, 0] * width + cb[:, 1]).size)


def wrap_quarter(angle: float) -> float:
    """``angle`` modulo 90°, in [-45°, 45°) (radians)."""
    return (angle + np.pi / 4) % (np.pi / 2) - np.pi / 4


def dominant_yaw(planes: list[Plane], cfg: PlaneFitConfig) -> float | None:
    """The yaw (radians, modulo 90°) most vertical planes agree on within ``yaw_snap_deg``,
    weighted by their points (a mode, so a few planes at other angles do not pull it)."""
    vertical = [p for p in planes if abs(p.normal[2]) < 1e-9]
    if not vertical or cfg.yaw_snap_deg == 0:
        return None
    phase = np.array([wrap_quarter(np.arctan2(p.normal[1], p.normal[0])) for p in vertical])
    weight = np.array([len(p.points) for p in vertical], dtype=float)
    apart = wrap_quarter(phase[None, :] - phase[:, None])  # [candidate, plane]
    near = np.abs(apart) < np.radians(cfg.yaw_snap_deg)
    best = int(np.argmax((near * weight).sum(axis=1)))
    return float(phase[best] + np.average(apart[best][near[best]], weights=weight[near[best]]))


def snap_yaw(planes: list[Plane], yaw: float | None, cfg: PlaneFitConfig) -> list[Plane]:
    """Vertical planes within ``yaw_snap_deg`` of the dominant yaw (modulo 90°) turned onto it."""
    if yaw is None:
        return planes
    for plane in planes:
        if abs(plane.normal[2]) > 1e-9:
            continue
        theta = np.arctan2(plane.normal[1], plane.normal[0])
        off = wrap_quarter(theta - yaw)
        if abs(off) < np.radians(cfg.yaw_snap_deg):
            plane.normal = np.array([np.cos(theta - off), np.sin(theta - off), 0.0])
            plane.offset = float(np.median(plane.points @ plane.normal))
    return planes


def merge_planes(planes: list[Plane], cfg: PlaneFitConfig) -> list[Plane]:
    """Coplanar planes whose footprints touch become one."""
    if len(planes) < 2:
        return planes
    normals = np.stack([p.normal for p in planes])
    offsets = np.array([p.offset for p in planes])
    candidate = (normals @ normals.T >= cfg.merge_normal_cosine) & \
        (np.abs(offsets[:, None] - offsets[None]) < cfg.same_surface_distance)
    rows, cols = np.nonzero(np.triu(candidate, 1))
    cell = max(cfg.merge_gap, cfg.footprint_cell)
    thin = {i: _thin(planes[i].points, cell) for i in np.union1d(rows, cols)}
    links = [(i, j) for i, j in zip(rows, cols) if _touching(thin[i], thin[j], planes[i].normal, cell)]
    if not links:
        return planes
    links = np.array(links)
    graph = coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(len(planes),) * 2)
    count, comp = connected_components(graph, directed=False)
    merged = []
    for c in range(count):
        members = [planes[i] for i in np.flatnonzero(comp == c)]
        if len(members) == 1:
            merged.append(members[0])
            continue
        weights = np.array([len(m.points) for m in members], dtype=float)
        normal = _snap((np.stack([m.normal for m in members]) * weights[:, None]).sum(axis=0), cfg)
        points = np.concatenate([m.points for m in members])
        merged.append(Plane(normal=normal, offset=float(np.median(points @ normal)), points=points,
                             frames=sum(m.frames for m in members), groups=[g for m in members for g in m.groups]))
    return merged
