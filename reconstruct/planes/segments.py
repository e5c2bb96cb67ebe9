"""Stage 1, per frame: the block-averaged pointmap on a coarse grid, its normals, orientation labels
by K-means and the planar segments (connected components of one orientation)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from sklearn.cluster import KMeans

from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.planes.config import PlaneFitConfig


@dataclass
class Grid:
    """One frame on the coarse grid."""

    points: np.ndarray  # (h, w, 3) float32 world points
    depth: np.ndarray  # (h, w) float32 camera z, 0 = no cell
    valid: np.ndarray  # (h, w) bool


def block_stride(width: int, cfg: PlaneFitConfig) -> int:
    return max(1, round(width / cfg.grid_width))


def frame_grid(frames: Frames, t: int, rays: np.ndarray, stride: int, cfg: PlaneFitConfig,
                pelvis_tree: cKDTree | None, dropped: dict[str, int]) -> Grid:
    """Block-averaged world pointmap of frame ``t`` with the depth and pelvis filters applied."""
    h, w = (s // stride for s in frames.image_size)
    depth = frames.depth[t, :h * stride, :w * stride]
    valid = depth > 0
    if cfg.depth_percentile < 100.0 and valid.any():
        values = depth[valid]
        k = min(len(values) - 1, int(np.ceil(cfg.depth_percentile / 100.0 * len(values))) - 1)
        limit = np.partition(values, max(k, 0))[max(k, 0)]
        far = valid & (depth > limit)
        valid &= ~far
        dropped["depth_percentile"] += int(far.sum())
    z = np.where(valid, depth, 0.0).astype(np.float32)
    # INTER_AREA at an integer factor is the exact block mean; divide by the valid fraction.
    def area(image: np.ndarray) -> np.ndarray:
        return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)

    fraction = area(valid.astype(np.float32))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = area(z[..., None] * rays[:h * stride, :w * stride]) / fraction[..., None]
        z_mean, z_sq = area(z) / fraction, area(z * z) / fraction
        spread = np.sqrt(np.maximum(z_sq - z_mean**2, 0.0))
        cell = (fraction >= cfg.min_block_fill) & (spread <= cfg.max_block_depth_std * z_mean)
    mean[~cell] = 0.0
    pose = frames.cam_c2w[t]
    world = (mean @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
    if pelvis_tree is not None and cell.any():
        dist, _ = pelvis_tree.query(world[cell], distance_upper_bound=cfg.pelvis_radius)
        far = np.isinf(dist)
        dropped["pelvis"] += int(far.sum())
        idx = np.flatnonzero(cell)[far]
        cell.flat[idx] = False
    return Grid(points=world, depth=np.where(cell, mean[..., 2], 0.0).astype(np.float32), valid=cell)


def grid_normals(grid: Grid, camera: np.ndarray, cfg: PlaneFitConfig) -> tuple[np.ndarray, np.ndarray]:
    """(h, w, 3) unit normals towards the camera, and (h, w) where they are defined."""
    s = cfg.normal_step
    p, ok = grid.points, grid.valid
    h, w = ok.shape
    normals = np.zeros((h, w, 3), dtype=np.float32)
    has = np.zeros((h, w), dtype=bool)
    if h <= 2 * s or w <= 2 * s:
        return normals, has
    c = p[s:-s, s:-s]
    left, right = p[s:-s, :-2 * s], p[s:-s, 2 * s:]
    up, down = p[:-2 * s, s:-s], p[2 * s:, s:-s]
    inner = ok[s:-s, s:-s] & ok[s:-s, :-2 * s] & ok[s:-s, 2 * s:] & ok[:-2 * s, s:-s] & ok[2 * s:, s:-s]
    du, dv = right - left, down - up
    len_u, len_v = np.linalg.norm(du, axis=-1), np.linalg.norm(dv, axis=-1)
    n = np.cross(du, dv)
    len_n = np.linalg.norm(n, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        flat = ((np.linalg.norm(right + left - 2 * c, axis=-1) <= cfg.max_planarity_residual * len_u)
                & (np.linalg.norm(down + up - 2 * c, axis=-1) <= cfg.max_planarity_residual * len_v))
        n = n / len_n[..., None]
    inner &= flat & (len_n > 0)
    n = np.where((np.einsum("ijk,ijk->ij", n, camera - c) < 0)[..., None], -n, n)  # face the camera
    normals[s:-s, s:-s] = np.where(inner[..., None], n, 0.0)
    has[s:-s, s:-s] = inner
    return normals, has


def orientation_labels(normals: np.ndarray, has: np.ndarray, cfg: PlaneFitConfig,
                        rng: np.random.Generator) -> np.ndarray:
    """(h, w) orientation label per cell (-1 = none): K-means on the normals, close centres merged."""
    labels = np.full(has.shape, -1, dtype=np.int32)
    values = normals[has]
    if len(values) < cfg.min_segment_cells:
        return labels
    sample = values[rng.integers(0, len(values), cfg.kmeans_sample)] if len(values) > cfg.kmeans_sample else values
    # A clean render can have fewer distinct normals than K; K-means would then warn and duplicate.
    quantised = np.round(sample * 1000).astype(np.int64) + 1000
    k = min(cfg.kmeans_clusters, len(np.unique((quantised[:, 0] * 2001 + quantised[:, 1]) * 2001 + quantised[:, 2])))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        km = KMeans(n_clusters=k, n_init=1, max_iter=cfg.kmeans_iterations,
                    random_state=int(rng.integers(2**31 - 1))).fit(sample)
    centres = km.cluster_centers_ / np.linalg.norm(km.cluster_centers_, axis=1, keepdims=True)
    close = centres @ centres.T >= np.cos(np.radians(cfg.cluster_merge_deg))
    _, merged = connected_components(close, directed=False)
    cosine = values @ centres.T.astype(np.float32)
    nearest = np.argmax(cosine, axis=1)
    keep = cosine[np.arange(len(values)), nearest] >= np.cos(np.radians(cfg.max_normal_deviation_deg))
    labels[has] = np.where(keep, merged[nearest], -1)
    return labels


def planar_segments(labels: np.ndarray, cfg: PlaneFitConfig) -> tuple[np.ndarray, int]:
    """(h, w) segment id per cell (-1 = none, else 0..n-1) from connected components per label."""
    out = np.full(labels.shape, -1, dtype=np.int32)
    count = 0
    for label in np.unique(labels[labels >= 0]):
        n, cc, stats, _ = cv2.connectedComponentsWithStats((labels == label).astype(np.uint8), connectivity=4)
        big = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= cfg.min_segment_cells) + 1
        lut = np.full(n, -1, dtype=np.int32)
        lut[big] = count + np.arange(len(big), dtype=np.int32)
        mapped = lut[cc]
        out = np.where(mapped >= 0, mapped, out)
        count += len(big)
    return out, count


def grow_segments(segments: np.ndarray, count: int, grid: Grid, normals: np.ndarray, has: np.ndarray,
          cfg: PlaneFitConfig) -> np.ndarray:
    """Segments extended into adjacent cells without a normal that lie on the segment's plane."""
    if count == 0 or cfg.grow_cells == 0:
        return segments
    labelled = segments >= 0
    ids = segments[labelled]
    plane = np.stack([np.bincount(ids, weights=normals[labelled][:, i], minlength=count) for i in range(3)], axis=1)
    plane /= np.maximum(np.linalg.norm(plane, axis=1, keepdims=True), 1e-12)
    offset = np.bincount(ids, weights=np.einsum("ij,ij->i", grid.points[labelled], plane[ids]), minlength=count)
    offset /= np.maximum(np.bincount(ids, minlength=count), 1)
    segments = segments.copy()
    free = grid.valid & ~has
    for _ in range(cfg.grow_cells):
        for axis, shift in ((0, 1), (0, -1), (1, 1), (1, -1)):
            neighbour = np.roll(segments, shift, axis=axis)
            edge = [slice(None)] * 2
            edge[axis] = 0 if shift == 1 else -1
            neighbour[tuple(edge)] = -1  # no wrap-around
            rows, cols = np.nonzero(free & (segments < 0) & (neighbour >= 0))
            cand = neighbour[rows, cols]
            dist = np.abs(np.einsum("ij,ij->i", grid.points[rows, cols], plane[cand]) - offset[cand])
            near = dist <= cfg.grow_distance
            segments[rows[near], cols[near]] = cand[near]
    return segments
