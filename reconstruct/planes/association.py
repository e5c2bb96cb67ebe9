"""Stage 2, across frames: a segment's cells reprojected into earlier frames, and the segments they
overlap there with agreeing normals and coinciding planes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crisp_gym.reconstruct.planes.config import PlaneFitConfig


@dataclass
class Seen:
    """What later frames need of an earlier one to associate with it."""

    segments: np.ndarray  # (h, w) global segment id, -1 = none
    depth: np.ndarray  # (h, w) camera z of the cells, 0 = none
    world_to_cam: np.ndarray  # (4, 4)


def associate(points: np.ndarray, ids: np.ndarray, seen: Seen, intrinsic: np.ndarray, stride: int,
               sizes: np.ndarray, normals: np.ndarray, centroids: np.ndarray, cfg: PlaneFitConfig) -> np.ndarray:
    """(E, 2) links between the current frame's segments (cells ``points`` with global ``ids``)
    and the segments of an earlier frame ``seen``."""
    cam = points @ seen.world_to_cam[:3, :3].T + seen.world_to_cam[:3, 3]
    h, w = seen.depth.shape
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.floor((intrinsic[0, 0] * cam[:, 0] / cam[:, 2] + intrinsic[0, 2]) / stride)
        v = np.floor((intrinsic[1, 1] * cam[:, 1] / cam[:, 2] + intrinsic[1, 2]) / stride)
    inside = (cam[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z, b = u[inside].astype(np.int64), v[inside].astype(np.int64), cam[inside, 2], ids[inside]
    there = seen.depth[v, u]
    covisible = (there > 0) & (np.abs(there - z) <= cfg.association_depth_tolerance * z)
    b = b[covisible]
    a = seen.segments[v[covisible], u[covisible]]
    visible_b = np.bincount(b, minlength=len(sizes))
    on = a >= 0
    keys, counts = np.unique(a[on].astype(np.int64) * len(sizes) + b[on], return_counts=True)
    a, b = keys // len(sizes), keys % len(sizes)
    overlap = counts / np.maximum(np.minimum(visible_b[b], sizes[a]), 1)
    cosine = np.einsum("ij,ij->i", normals[a], normals[b])
    # each centroid on the other's plane: parallel surfaces a step apart overlap along their edges
    apart = np.maximum(np.abs(np.einsum("ij,ij->i", normals[a], centroids[b] - centroids[a])),
                       np.abs(np.einsum("ij,ij->i", normals[b], centroids[a] - centroids[b])))
    keep = (overlap >= cfg.min_overlap) & (counts >= cfg.min_overlap_cells) & (cosine >= cfg.min_normal_cosine) \
        & (apart <= cfg.association_plane_distance)
    return np.stack([a[keep], b[keep]], axis=1)
