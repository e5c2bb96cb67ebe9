"""Planar fitting: a metric, gravity-aligned depth video → box primitives (paper Sec. 3.2 and its
appendix "Details of planar fitting"), made fast.

The stages, each vectorised with numpy/OpenCV:

1. **Per frame**, on a coarse grid: the pointmap is block-averaged (this is the smoothing: a block
   of r×r pixels averages r² depth samples), points beyond the frame's depth percentile and far
   from the pelvis path are dropped, normals come from finite differences over a few cells, cells
   on creases and depth edges (where the pointmap is not locally flat) get none, K-means on the
   normals (fit on a subsample, every cell assigned to its nearest centre; centres closer than a
   few degrees merged) labels orientations, and connected components of each orientation on the
   image grid are the frame's planar segments; small ones are dropped.
2. **Across frames**: the cells of each segment are reprojected into a few earlier frames with the
   camera poses; where the reprojected depth agrees with what that frame saw, the segment under it
   overlaps. Segments that overlap enough, whose normals agree and whose planes coincide are
   linked; connected components of the link graph (union-find) are the global planar groups.
3. **Per group**: a RANSAC plane normal, snapped to gravity when within a few degrees of vertical
   or horizontal. Monocular depth drifts in scale from frame to frame, so each frame's depth is
   then rescaled (about its camera) to put its segments on the planes the whole video agrees on;
   the segments' planes that chain together are one surface (a group that chained two parallel
   surfaces a step apart gives both), its inliers the cells near their own segment's plane.
   Vertical planes close to the scene's dominant yaw are turned onto it, and coplanar planes that
   touch are merged.
4. **Per plane**: the inliers' footprint on an occupancy grid, its minimum-area rectangle (edges
   horizontal and vertical for vertical surfaces), split into rectangles by guillotine cuts where
   a notch is missing from it, and a box of the paper's 0.05 m thickness *behind* each rectangle
   (away from the cameras), so its visible face is where the points are. The floor is one box.

Input: :class:`~crisp_gym.reconstruct.frames.Frames` already metric, gravity-aligned (z up, floor at z = 0)
with person pixels removed (depth 0), and optionally the pelvis path (N, 3) of the person.
"""

from __future__ import annotations

import heapq
import itertools
import time
import warnings
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from sklearn.cluster import KMeans
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from crisp_gym.geometry import min_area_rectangle, plane_axes, ransac_plane, snap_to_gravity
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.scene import Box

_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class PlaneFitConfig:
    """Every threshold of :func:`fit_planes` (lengths in metres, angles in degrees).

    Attributes:
        grid_width: the pointmap is block-averaged to about this many cells across (block side =
            ``round(W / grid_width)`` pixels); all per-frame work runs on this grid.
        min_block_fill: a block needs this fraction of valid pixels to become a cell.
        max_block_depth_std: a block whose depth standard deviation exceeds this fraction of its
            mean straddles a depth edge and is dropped (its average would float between surfaces).
        normal_step: half-width, in grid cells, of the finite differences that give normals.
        max_planarity_residual: a cell whose two neighbours ``normal_step`` cells away do not lie
            on a line through it, ``|p₊ + p₋ - 2p| / |p₊ - p₋|`` above this along either image
            axis, sits on a crease or depth edge and gets no normal.
        grow_cells: segments then grow this many cells into neighbouring cells without a normal
            (the rims along creases and edges that finite differences cannot see)...
        grow_distance: ...when those lie within this distance of the segment's plane.
        depth_percentile: per frame, points deeper than this percentile of its valid depths are
            dropped (far, noisy background).
        pelvis_radius: with a pelvis path, points farther than this (3D) from it are dropped.
        kmeans_clusters: K of the per-frame K-means on normals.
        kmeans_sample: number of normals (per frame) the K-means is fit on.
        kmeans_iterations: K-means iteration cap.
        cluster_merge_deg: K-means centres closer than this are one orientation (K larger than the
            number of orientations in view otherwise splits one surface's noisy normals).
        max_normal_deviation_deg: a cell whose normal is farther than this from its centre is
            left unlabelled.
        min_segment_cells: connected components smaller than this (grid cells) are dropped.
        association_offsets: each frame's segments are matched against the frames this many
            frames earlier.
        association_depth_tolerance: a reprojected cell is seen by the earlier frame when the
            depths agree within this fraction of the depth.
        min_overlap: link two segments when their overlap is at least this fraction of the
            smaller one (counted on the reprojected cells)...
        min_overlap_cells: ...and at least this many cells...
        min_normal_cosine: ...and their mean normals have at least this cosine (also the largest
            angle a RANSAC plane may make with its group's mean normal)...
        association_plane_distance: ...and each one's centroid is within this distance of the
            other's plane (frames a moment apart agree on where a surface is; a tread and the next
            one up overlap along their shared edge but are a riser apart).
        min_group_frames: planar groups (and surfaces) seen in fewer frames are dropped...
        single_view_share: ...unless their inliers cover at least this share of one frame's grid
            (a surface seen well once is still a surface: sparse keyframes, or a table top one
            view saw; what a video sees in a frame or two without linking it is small).
        min_group_points: planar groups (and surfaces) with fewer inlier points are dropped.
        ransac_distance: RANSAC inlier distance to the plane; also the distance within which a
            cell is an inlier of its frame's segment plane.
        ransac_iterations: RANSAC hypotheses per group.
        ransac_sample: hypotheses are scored on at most this many points of the group.
        frame_scale_correction: each frame's depth may be rescaled about its camera by up to this
            fraction so that its segments lie on the planes the whole video agrees on (monocular
            depth drifts in scale from frame to frame); 0 disables it.
        yaw_snap_deg: vertical planes, and the rectangles of horizontal ones, whose yaw is within
            this of the scene's dominant yaw (modulo 90°, from the vertical planes) are snapped to
            it: box scenes are mostly built square to each other; 0 disables it.
        snap_deg: normals within this angle of vertical become exactly vertical, within this angle
            of horizontal exactly horizontal (the input is gravity-aligned).
        merge_normal_cosine: planes with normals at least this close are parallel.
        same_surface_distance: parallel planes whose offsets differ by less than this are one
            surface (monocular depth spreads a surface over a few centimetres from frame to frame):
            a group's segments whose planes chain together with gaps below this are one surface,
            and planes of different groups this close whose footprints touch are merged.
        merge_gap: footprints closer than this touch.
        floor_height: an upward-facing horizontal plane within this of z = 0 is the floor (the
            alignment puts it there): one box over its whole footprint, never split, because its
            holes are occlusions by what stands on it.
        footprint_cell: occupancy-grid cell of the footprints.
        footprint_closing: gaps in a footprint up to about this wide are closed (far and grazing
            surfaces are sampled sparsely on the grid).
        min_footprint_area: connected occupied areas smaller than this (m²) are outliers; split
            rectangles holding less are dropped.
        min_fill_ratio: a rectangle filled less than this by its footprint is split...
        min_split_gain: ...when a cut shrinks the covered area by at least this fraction of the
            rectangle...
        min_split_notch: ...by cutting off a notch at least this deep (m): a missing corner the
            size of a step is split off, the ragged or tapered edges of a noisy footprint are not.
            Of a split footprint, parts narrower than this are dropped (strips along an edge where
            views disagree by a few centimetres, not surfaces).
        max_boxes_per_plane: at most this many boxes per plane (splitting stops there).
        thickness: box thickness behind the surface (the paper's 0.05 m).
        seed: seeds K-means and RANSAC, so runs are reproducible.
    """

    grid_width: int = 128
    min_block_fill: float = 0.5
    max_block_depth_std: float = 0.03
    normal_step: int = 1
    max_planarity_residual: float = 0.3
    grow_cells: int = 3
    grow_distance: float = 0.02
    depth_percentile: float = 95.0
    pelvis_radius: float = 2.5
    kmeans_clusters: int = 6
    kmeans_sample: int = 2048
    kmeans_iterations: int = 30
    cluster_merge_deg: float = 15.0
    max_normal_deviation_deg: float = 30.0
    min_segment_cells: int = 8
    association_offsets: tuple[int, ...] = (1, 4)
    association_depth_tolerance: float = 0.05
    min_overlap: float = 0.25
    min_overlap_cells: int = 8
    min_normal_cosine: float = 0.95
    association_plane_distance: float = 0.05
    min_group_frames: int = 3
    single_view_share: float = 0.03
    min_group_points: int = 150
    ransac_distance: float = 0.03
    ransac_iterations: int = 200
    ransac_sample: int = 4096
    frame_scale_correction: float = 0.1
    snap_deg: float = 10.0
    yaw_snap_deg: float = 5.0
    merge_normal_cosine: float = 0.99
    same_surface_distance: float = 0.08
    merge_gap: float = 0.05
    floor_height: float = 0.05
    footprint_cell: float = 0.02
    footprint_closing: float = 0.1
    min_footprint_area: float = 0.01
    min_fill_ratio: float = 0.9
    min_split_gain: float = 0.05
    min_split_notch: float = 0.1
    max_boxes_per_plane: int = 8
    thickness: float = 0.05
    seed: int = 0

    def __post_init__(self) -> None:
        positive_ints = ("grid_width", "normal_step", "kmeans_clusters", "kmeans_sample", "kmeans_iterations",
                         "min_segment_cells", "min_overlap_cells", "min_group_frames", "min_group_points",
                         "ransac_iterations", "ransac_sample", "max_boxes_per_plane")
        for name in positive_ints:
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"PlaneFitConfig.{name} must be a positive integer, got {value!r}")
        positive = ("max_block_depth_std", "max_planarity_residual", "grow_distance", "pelvis_radius",
                    "cluster_merge_deg", "max_normal_deviation_deg", "association_depth_tolerance",
                    "association_plane_distance", "ransac_distance", "same_surface_distance", "floor_height",
                    "footprint_cell", "min_footprint_area", "min_split_notch", "thickness")
        for name in positive:
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"PlaneFitConfig.{name} must be positive and finite, got {value!r}")
        fractions = ("min_block_fill", "min_overlap", "min_normal_cosine", "merge_normal_cosine", "min_fill_ratio",
                     "single_view_share")
        for name in fractions:
            value = getattr(self, name)
            if not 0.0 < value <= 1.0:
                raise ValueError(f"PlaneFitConfig.{name} must be in (0, 1], got {value!r}")
        if not 0.0 <= self.min_split_gain < 1.0:
            raise ValueError(f"PlaneFitConfig.min_split_gain must be in [0, 1), got {self.min_split_gain!r}")
        if not 0.0 < self.depth_percentile <= 100.0:
            raise ValueError(f"PlaneFitConfig.depth_percentile must be in (0, 100], got {self.depth_percentile!r}")
        if not 0.0 <= self.frame_scale_correction < 1.0:
            raise ValueError(f"PlaneFitConfig.frame_scale_correction must be in [0, 1), got "
                             f"{self.frame_scale_correction!r}")
        for name in ("snap_deg", "yaw_snap_deg"):
            if not 0.0 <= getattr(self, name) < 45.0:
                raise ValueError(f"PlaneFitConfig.{name} must be in [0, 45), got {getattr(self, name)!r}")
        if not isinstance(self.grow_cells, (int, np.integer)) or self.grow_cells < 0:
            raise ValueError(f"PlaneFitConfig.grow_cells must be a non-negative integer, got {self.grow_cells!r}")
        for name in ("merge_gap", "footprint_closing"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"PlaneFitConfig.{name} must be >= 0, got {getattr(self, name)!r}")
        offsets = tuple(self.association_offsets)
        if not offsets or any(not isinstance(k, (int, np.integer)) or k < 1 for k in offsets):
            raise ValueError(f"PlaneFitConfig.association_offsets must be positive frame offsets, got {offsets!r}")
        object.__setattr__(self, "association_offsets", tuple(sorted({int(k) for k in offsets})))


@dataclass(frozen=True)
class PlaneInfo:
    """Diagnostics of one fitted plane.

    Attributes:
        normal: (3,) unit normal, pointing towards the cameras that saw it.
        offset: ``normal · p`` of the plane's points (m).
        points: number of grid points (over all frames) on the plane.
        frames: number of frames it was seen in.
        groups: ids of the planar groups merged into it.
        fill_ratio: footprint area / area of its minimum-area rectangle, before splitting.
        boxes: number of boxes it became.
    """

    normal: np.ndarray
    offset: float
    points: int
    frames: int
    groups: tuple[int, ...]
    fill_ratio: float
    boxes: int


@dataclass(frozen=True)
class PlaneFit:
    """What :func:`fit_planes` returns.

    Attributes:
        boxes: the fitted primitives (``source="planar"``); each box's local +z axis is its
            surface normal (towards the cameras) and its +z face is the fitted surface.
        planes: per-plane diagnostics, in the order of the boxes they produced.
        timings: seconds per stage (``segment``, ``associate``, ``planes``, ``boxes``, ``total``).
        segments: number of per-frame segments.
        groups: number of planar groups after association (before the size filters).
        frame_scales: (T,) the depth-scale correction applied to each frame (1 = none).
        dropped: what each filter removed: ``depth_percentile`` pixels, ``pelvis`` grid cells.
    """

    boxes: list[Box]
    planes: list[PlaneInfo]
    timings: dict[str, float]
    segments: int
    groups: int
    frame_scales: np.ndarray
    dropped: dict[str, int] = field(default_factory=dict)


# --------------------------------------------------------------------------- per frame


@dataclass
class _Grid:
    """One frame on the coarse grid."""

    points: np.ndarray  # (h, w, 3) float32 world points
    depth: np.ndarray  # (h, w) float32 camera z, 0 = no cell
    valid: np.ndarray  # (h, w) bool


def _block_stride(width: int, cfg: PlaneFitConfig) -> int:
    return max(1, round(width / cfg.grid_width))


def _frame_grid(frames: Frames, t: int, rays: np.ndarray, stride: int, cfg: PlaneFitConfig,
                pelvis_tree: cKDTree | None, dropped: dict[str, int]) -> _Grid:
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
    return _Grid(points=world, depth=np.where(cell, mean[..., 2], 0.0).astype(np.float32), valid=cell)


def _normals(grid: _Grid, camera: np.ndarray, cfg: PlaneFitConfig) -> tuple[np.ndarray, np.ndarray]:
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


def _orientation_labels(normals: np.ndarray, has: np.ndarray, cfg: PlaneFitConfig,
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


def _segments(labels: np.ndarray, cfg: PlaneFitConfig) -> tuple[np.ndarray, int]:
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


def _grow(segments: np.ndarray, count: int, grid: _Grid, normals: np.ndarray, has: np.ndarray,
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


# --------------------------------------------------------------------------- across frames


@dataclass
class _Seen:
    """What later frames need of an earlier one to associate with it."""

    segments: np.ndarray  # (h, w) global segment id, -1 = none
    depth: np.ndarray  # (h, w) camera z of the cells, 0 = none
    world_to_cam: np.ndarray  # (4, 4)


def _associate(points: np.ndarray, ids: np.ndarray, seen: _Seen, intrinsic: np.ndarray, stride: int,
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


# --------------------------------------------------------------------------- planes


def _snap(normal: np.ndarray, cfg: PlaneFitConfig) -> np.ndarray:
    """Exactly vertical / horizontal when within ``snap_deg`` of it (gravity-aligned input)."""
    return snap_to_gravity(normal / np.linalg.norm(normal), cfg.snap_deg)


def _ransac_normal(points: np.ndarray, prior: np.ndarray, cfg: PlaneFitConfig,
                   rng: np.random.Generator) -> np.ndarray:
    """Normal (towards ``prior``) of the RANSAC plane with the most inliers among hypotheses within
    the normal tolerance of ``prior``, refined by least squares on its inliers and snapped."""
    sample = points[rng.integers(0, len(points), cfg.ransac_sample)] if len(points) > cfg.ransac_sample else points
    found = ransac_plane(sample, prior, cfg.min_normal_cosine, cfg.ransac_distance, cfg.ransac_iterations, rng,
                         refinements=1)
    return _snap(prior if found is None else found[0], cfg)  # none: too few points to disagree with the prior


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value below and above which half the weight lies."""
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])




@dataclass
class _Plane:
    """A fitted plane: ``normal · p = offset`` for its inlier ``points``."""

    normal: np.ndarray
    offset: float
    points: np.ndarray  # (N, 3) inliers
    frames: int
    groups: list[int]


def _cells(uv: np.ndarray, cell: float) -> np.ndarray:
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
    ca, cb = _cells(a @ basis.T, cell), _cells(b @ basis.T, cell)
    low = np.minimum(ca.min(axis=0), cb.min(axis=0)) - 1
    ca, cb = ca - low, cb - low
    width = max(ca[:, 1].max(), cb[:, 1].max()) + 2
    shifts = np.array([i * width + j for i in (-1, 0, 1) for j in (-1, 0, 1)])
    grown = (ca[:, 0] * width + ca[:, 1])[:, None] + shifts[None]
    return bool(np.intersect1d(grown.ravel(), cb[:, 0] * width + cb[:, 1]).size)


def _wrap_quarter(angle: float) -> float:
    """``angle`` modulo 90°, in [-45°, 45°) (radians)."""
    return (angle + np.pi / 4) % (np.pi / 2) - np.pi / 4


def _dominant_yaw(planes: list[_Plane], cfg: PlaneFitConfig) -> float | None:
    """The yaw (radians, modulo 90°) most vertical planes agree on within ``yaw_snap_deg``,
    weighted by their points (a mode, so a few planes at other angles do not pull it)."""
    vertical = [p for p in planes if abs(p.normal[2]) < 1e-9]
    if not vertical or cfg.yaw_snap_deg == 0:
        return None
    phase = np.array([_wrap_quarter(np.arctan2(p.normal[1], p.normal[0])) for p in vertical])
    weight = np.array([len(p.points) for p in vertical], dtype=float)
    apart = _wrap_quarter(phase[None, :] - phase[:, None])  # [candidate, plane]
    near = np.abs(apart) < np.radians(cfg.yaw_snap_deg)
    best = int(np.argmax((near * weight).sum(axis=1)))
    return float(phase[best] + np.average(apart[best][near[best]], weights=weight[near[best]]))


def _snap_yaw(planes: list[_Plane], yaw: float | None, cfg: PlaneFitConfig) -> list[_Plane]:
    """Vertical planes within ``yaw_snap_deg`` of the dominant yaw (modulo 90°) turned onto it."""
    if yaw is None:
        return planes
    for plane in planes:
        if abs(plane.normal[2]) > 1e-9:
            continue
        theta = np.arctan2(plane.normal[1], plane.normal[0])
        off = _wrap_quarter(theta - yaw)
        if abs(off) < np.radians(cfg.yaw_snap_deg):
            plane.normal = np.array([np.cos(theta - off), np.sin(theta - off), 0.0])
            plane.offset = float(np.median(plane.points @ plane.normal))
    return planes


def _merge_planes(planes: list[_Plane], cfg: PlaneFitConfig) -> list[_Plane]:
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
        merged.append(_Plane(normal=normal, offset=float(np.median(points @ normal)), points=points,
                             frames=sum(m.frames for m in members), groups=[g for m in members for g in m.groups]))
    return merged


# --------------------------------------------------------------------------- footprints → boxes


def _occupancy(ab: np.ndarray, cfg: PlaneFitConfig) -> tuple[np.ndarray, np.ndarray]:
    """Occupancy grid of 2D points, closed (far and grazing surfaces are sampled sparsely) and
    cleaned of specks; and each point's cell in it, (-1, -1) for points in removed specks."""
    pad = round(cfg.footprint_closing / cfg.footprint_cell)
    cells = _cells(ab, cfg.footprint_cell)
    cells -= cells.min(axis=0) - pad
    occ = np.zeros(cells.max(axis=0) + 1 + pad, dtype=np.uint8)
    occ[cells[:, 0], cells[:, 1]] = 1
    if pad:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * pad + 1,) * 2)
        occ = cv2.morphologyEx(occ, cv2.MORPH_CLOSE, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    n, cc, stats, _ = cv2.connectedComponentsWithStats(occ, connectivity=8)
    big = np.zeros(n, dtype=bool)
    big[1:] = stats[1:, cv2.CC_STAT_AREA] * cfg.footprint_cell**2 >= cfg.min_footprint_area
    occ = big[cc]
    cells[~occ[cells[:, 0], cells[:, 1]]] = -1
    return occ, cells


def _trim(occ: np.ndarray, rs: slice, cs: slice) -> tuple[slice, slice] | None:
    """The bounding box of the occupied cells of ``occ[rs, cs]`` (None if there are none)."""
    part = occ[rs, cs]
    rows, cols = np.flatnonzero(part.any(axis=1)), np.flatnonzero(part.any(axis=0))
    if len(rows) == 0:
        return None
    return (slice(rs.start + rows[0], rs.start + rows[-1] + 1), slice(cs.start + cols[0], cs.start + cols[-1] + 1))


def _cuts(occ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For cutting ``occ`` between rows k-1 and k (k = 1..n-1): the summed bounding-box areas of
    the two parts, and how much narrower (columns) the narrower part's box is than ``occ``."""
    def prefix(grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        any_row = grid.any(axis=1)
        first_row = np.argmax(any_row)
        last_row = np.maximum.accumulate(np.where(any_row, np.arange(len(grid)), -1))
        cum = np.logical_or.accumulate(grid, axis=0)
        width = grid.shape[1] - np.argmax(cum[:, ::-1], axis=1) - np.argmax(cum, axis=1)
        has = cum.any(axis=1)
        return np.where(has, (last_row - first_row + 1) * width, 0), np.where(has, width, 0)
    area_before, width_before = prefix(occ)
    area_after, width_after = prefix(occ[::-1])
    narrowest = np.minimum(width_before[:-1], width_after[:-1][::-1])
    return area_before[:-1] + area_after[:-1][::-1], occ.shape[1] - narrowest


def _guillotine(occ: np.ndarray, cfg: PlaneFitConfig) -> list[tuple[slice, slice]]:
    """Split the occupied grid into well-filled axis-aligned rectangles (row, column slices),
    always splitting next the rectangle that covers the most empty cells."""
    min_cells = cfg.min_footprint_area / cfg.footprint_cell**2
    min_notch = cfg.min_split_notch / cfg.footprint_cell
    leaves, heap, order = [], [], 0
    root = _trim(occ, slice(0, occ.shape[0]), slice(0, occ.shape[1]))
    if root is not None:
        heap.append((-(occ[root].size - occ[root].sum()), order, root))
    while heap:
        _, _, (rs, cs) = heapq.heappop(heap)
        part = occ[rs, cs]
        area = part.size
        if part.sum() >= cfg.min_fill_ratio * area or min(part.shape) < 2 \
                or len(leaves) + len(heap) + 2 > cfg.max_boxes_per_plane:
            leaves.append((rs, cs))
            continue
        best = None  # (remaining area, axis, k) of the best cut that removes a deep enough notch
        for axis, grid in enumerate((part, part.T)):
            areas, notch = _cuts(grid)
            areas = np.where(notch >= min_notch, areas, np.iinfo(np.int64).max)
            k = int(np.argmin(areas))
            if best is None or areas[k] < best[0]:
                best = (int(areas[k]), axis, k + 1)
        if best is None or area - best[0] < cfg.min_split_gain * area:
            leaves.append((rs, cs))
            continue
        _, axis, k = best
        halves = [(slice(rs.start, rs.start + k), cs), (slice(rs.start + k, rs.stop), cs)] if axis == 0 else \
            [(rs, slice(cs.start, cs.start + k)), (rs, slice(cs.start + k, cs.stop))]
        for half in halves:
            child = _trim(occ, *half)
            if child is not None and occ[child].sum() >= min_cells:
                order += 1
                heapq.heappush(heap, (-(occ[child].size - occ[child].sum()), order, child))
    kept = [leaf for leaf in leaves if occ[leaf].sum() >= min_cells]
    if len(kept) > 1:
        kept = [leaf for leaf in kept if min(occ[leaf].shape) >= min_notch]
    return kept


def _plane_boxes(plane: _Plane, yaw: float | None, cfg: PlaneFitConfig) -> tuple[list[Box], float]:
    """Boxes behind the plane's footprint, and the footprint's fill ratio of its rectangle (whose
    yaw snaps to the scene's dominant ``yaw`` when the plane is horizontal and close to it)."""
    basis = plane_axes(plane.normal)
    uv = plane.points @ basis.T
    occ, cells = _occupancy(uv, cfg)
    if not occ.any():
        return [], 0.0
    if abs(plane.normal[2]) < 1e-9:
        axes = np.eye(2)  # vertical surface: edges horizontal and vertical
    else:
        corners = min_area_rectangle(np.argwhere(occ)).corners
        first = (corners[1] - corners[0]).astype(float)
        first = first / np.linalg.norm(first) if np.linalg.norm(first) > 0 else np.array([1.0, 0.0])
        if yaw is not None and abs(plane.normal[2]) > 1 - 1e-9:
            world = first @ basis
            angle = np.arctan2(world[1], world[0])
            off = _wrap_quarter(angle - yaw)
            if abs(off) < np.radians(cfg.yaw_snap_deg):
                first = basis @ np.array([np.cos(angle - off), np.sin(angle - off), 0.0])
        axes = np.stack([first, [-first[1], first[0]]])
    ab = uv[cells[:, 0] >= 0] @ axes.T
    occ, cells = _occupancy(ab, cfg)
    live = cells[:, 0] >= 0
    ab, cells = ab[live], cells[live]
    whole = _trim(occ, slice(0, occ.shape[0]), slice(0, occ.shape[1]))
    if whole is None:
        return [], 0.0
    fill = float(occ[whole].mean())
    floor = plane.normal[2] > 0.5 and abs(plane.offset) <= cfg.floor_height
    pieces = [whole] if floor else _guillotine(occ, cfg)
    x_axis = axes[0] @ basis
    rotation = np.stack([x_axis, np.cross(plane.normal, x_axis), plane.normal], axis=1)
    boxes = []
    for rs, cs in pieces:
        inside = (cells[:, 0] >= rs.start) & (cells[:, 0] < rs.stop) & (cells[:, 1] >= cs.start) & (cells[:, 1] < cs.stop)
        if not inside.any():
            continue
        lo, hi = ab[inside].min(axis=0), ab[inside].max(axis=0)
        half = np.maximum((hi - lo) / 2, cfg.footprint_cell / 2)
        centre = (plane.offset - 0.5 * cfg.thickness) * plane.normal + ((lo + hi) / 2) @ axes @ basis
        boxes.append(Box(center=centre, rotation=rotation, half_size=[half[0], half[1], cfg.thickness / 2],
                         source="planar"))
    return boxes, fill


# --------------------------------------------------------------------------- driver


def _pelvis_tree(pelvis_path: np.ndarray, spacing: float = 0.05) -> cKDTree:
    """KD-tree over the pelvis path densified to ``spacing``, so distances are to the polyline."""
    path = np.asarray(pelvis_path, dtype=float)
    if path.ndim != 2 or path.shape[1] != 3 or len(path) == 0:
        raise ValueError(f"pelvis_path must be (N, 3) with N >= 1, got shape {path.shape}")
    if not np.all(np.isfinite(path)):
        raise ValueError("pelvis_path contains NaN or infinite values")
    pieces = [path[:1]]
    for a, b in itertools.pairwise(path):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
        pieces.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return cKDTree(np.concatenate(pieces))


@dataclass
class _Segmented:
    """All frames' segments: per segment its frame, size (cells), mean normal and centroid; per
    labelled cell its world point and segment; and the links found between segments of different
    frames."""

    frame: np.ndarray
    size: np.ndarray
    normal: np.ndarray
    centroid: np.ndarray
    points: np.ndarray
    ids: np.ndarray
    links: np.ndarray
    cells_per_frame: int


def _segment_video(frames: Frames, tree: cKDTree | None, cfg: PlaneFitConfig, rng: np.random.Generator,
                   timings: dict[str, float], dropped: dict[str, int], progress: bool) -> _Segmented:
    """Stages 1 and 2: per-frame segments, and their links to the segments of earlier frames."""
    stride = _block_stride(frames.image_size[1], cfg)
    rays = frames.rays().astype(np.float32)
    seg_frame, seg_size, seg_normal, seg_centroid, links = [], [], [], [], []
    cell_points, cell_ids = [], []
    recent: dict[int, _Seen] = {}
    total = 0
    for t in tqdm(range(frames.num_frames), desc="planes: frames", unit="frame", disable=not progress):
        tic = time.perf_counter()
        pose = frames.cam_c2w[t]
        grid = _frame_grid(frames, t, rays, stride, cfg, tree, dropped)
        normals, has = _normals(grid, pose[:3, 3].astype(np.float32), cfg)
        segments, count = _segments(_orientation_labels(normals, has, cfg, rng), cfg)
        segments = _grow(segments, count, grid, normals, has, cfg)
        labelled = segments >= 0
        local = segments[labelled]
        points = grid.points[labelled]
        sums = np.stack([np.bincount(local, weights=normals[labelled][:, i], minlength=count) for i in range(3)],
                        axis=1)
        sizes = np.bincount(local, minlength=count)
        seg_frame.append(np.full(count, t))
        seg_size.append(sizes)
        seg_normal.append(sums / np.maximum(np.linalg.norm(sums, axis=1, keepdims=True), 1e-12))
        seg_centroid.append(np.stack([np.bincount(local, weights=points[:, i], minlength=count) for i in range(3)],
                                     axis=1) / np.maximum(sizes, 1)[:, None])
        cell_points.append(points)
        cell_ids.append(local + total)
        timings["segment"] += time.perf_counter() - tic
        tic = time.perf_counter()
        if count:
            known = [np.concatenate(x) for x in (seg_size, seg_normal, seg_centroid)]
            for k in cfg.association_offsets:
                if t - k in recent:
                    links.append(_associate(cell_points[-1], cell_ids[-1], recent[t - k], frames.intrinsic, stride,
                                            *known, cfg))
        recent[t] = _Seen(segments=np.where(labelled, segments + total, -1), depth=grid.depth,
                          world_to_cam=np.linalg.inv(pose))
        recent.pop(t - max(cfg.association_offsets), None)
        total += count
        timings["associate"] += time.perf_counter() - tic
    return _Segmented(frame=np.concatenate(seg_frame), size=np.concatenate(seg_size),
                      normal=np.concatenate(seg_normal), centroid=np.concatenate(seg_centroid), points=np.concatenate(cell_points).astype(np.float64),
                      ids=np.concatenate(cell_ids),
                      links=np.concatenate(links) if links else np.zeros((0, 2), dtype=np.int64),
                      cells_per_frame=int(grid.depth.size))


def _frame_scales(seg: _Segmented, group_of: np.ndarray, normal: np.ndarray, fitted: np.ndarray,
                  cameras: np.ndarray, cfg: PlaneFitConfig) -> np.ndarray:
    """(T,) per-frame depth scale, about each camera centre, that puts the frame's segments onto the
    planes of their groups (each group's offset being the median over the video)."""
    scales = np.ones(len(cameras))
    if cfg.frame_scale_correction == 0:
        return scales
    used = np.flatnonzero(fitted[group_of])
    group, frame, weight = group_of[used], seg.frame[used], seg.size[used].astype(float)
    n, cam = normal[group], cameras[frame]
    reach = np.einsum("ij,ij->i", n, seg.centroid[used] - cam)  # camera → segment along the normal
    steady = np.abs(reach) > 0.2  # a plane through the camera says nothing about scale
    for _ in range(2):  # the group offsets, then the scales; twice, so the offsets use corrected frames
        offset = np.einsum("ij,ij->i", n, cam) + scales[frame] * reach
        target = np.zeros(len(normal))
        for g in np.unique(group):
            mine = group == g
            target[g] = _weighted_median(offset[mine], weight[mine])
        wanted = (target[group] - np.einsum("ij,ij->i", n, cam)) / np.where(steady, reach, 1.0)
        for t in np.unique(frame[steady]):
            mine = steady & (frame == t)
            scales[t] = _weighted_median(wanted[mine], weight[mine])
    return np.clip(scales, 1 - cfg.frame_scale_correction, 1 + cfg.frame_scale_correction)


def _seen_enough(cell_frames: np.ndarray, cells_per_frame: int, cfg: PlaneFitConfig) -> bool:
    """A group or surface whose inlier cells were seen in frames ``cell_frames`` is kept: enough
    cells, and seen in enough frames or well in one."""
    if len(cell_frames) < cfg.min_group_points:
        return False
    per_frame = np.unique(cell_frames, return_counts=True)[1]
    return len(per_frame) >= cfg.min_group_frames or per_frame.max() >= cfg.single_view_share * cells_per_frame


def _group_planes(seg: _Segmented, cameras: np.ndarray, cfg: PlaneFitConfig,
                  rng: np.random.Generator) -> tuple[list[_Plane], int, np.ndarray]:
    """Stage 3: union-find of linked segments into groups; per group a RANSAC normal; per frame a
    depth-scale correction; per group the surfaces its segments lie on and their inliers; then
    coplanar planes that touch are merged. Returns the planes, the number of groups and the
    per-frame scales.

    Monocular depth puts one surface a few centimetres apart from one moment to the next (scale
    drift). The frame scales take out most of it; what remains is handled per segment: each
    segment is a plane of its own along the group's normal (the median offset of its cells), its
    cells within ``ransac_distance`` of it are inliers, and segments whose offsets chain together
    without a gap wider than ``same_surface_distance`` are one surface, at the (inlier-weighted)
    median offset. A group that chained two parallel surfaces a step apart thus gives both.
    """
    total = len(seg.frame)
    if total == 0:
        return [], 0, np.ones(len(cameras))
    graph = coo_matrix((np.ones(len(seg.links)), (seg.links[:, 0], seg.links[:, 1])), shape=(total, total))
    num_groups, group_of = connected_components(graph, directed=False)
    weighted = seg.size[:, None] * seg.normal
    group_normal = np.stack([np.bincount(group_of, weights=weighted[:, i], minlength=num_groups)
                             for i in range(3)], axis=1)
    group = group_of[seg.ids]
    order = np.argsort(group, kind="stable")
    bounds = np.searchsorted(group[order], np.arange(num_groups + 1))
    normal = np.zeros((num_groups, 3))
    fitted = np.zeros(num_groups, dtype=bool)
    for g in range(num_groups):
        cells = order[bounds[g]:bounds[g + 1]]
        if not _seen_enough(seg.frame[seg.ids[cells]], seg.cells_per_frame, cfg):
            continue
        prior = group_normal[g] / max(np.linalg.norm(group_normal[g]), 1e-12)
        normal[g] = _ransac_normal(seg.points[cells], prior, cfg, rng)
        fitted[g] = True
    scales = _frame_scales(seg, group_of, normal, fitted, cameras, cfg)
    cell_frame = seg.frame[seg.ids]
    points = cameras[cell_frame] + scales[cell_frame, None] * (seg.points - cameras[cell_frame])
    planes = []
    for g in np.flatnonzero(fitted):
        cells = order[bounds[g]:bounds[g + 1]]
        members = points[cells]
        if cfg.frame_scale_correction > 0:  # drift spread the raw points: RANSAC again on corrected ones
            normal[g] = _ransac_normal(members, normal[g], cfg, rng)
        height = members @ normal[g]
        segments, local = np.unique(seg.ids[cells], return_inverse=True)
        by_segment = np.lexsort((height, local))
        starts = np.searchsorted(local[by_segment], np.arange(len(segments)))
        counts = np.bincount(local, minlength=len(segments))
        offset = height[by_segment[starts + counts // 2]]  # per-segment median
        inlier = np.abs(height - offset[local]) < cfg.ransac_distance
        weight = np.bincount(local[inlier], minlength=len(segments)).astype(float)
        ranked = np.argsort(offset)
        surface = np.empty(len(segments), dtype=np.int64)
        surface[ranked] = np.concatenate([[0], np.cumsum(np.diff(offset[ranked]) > cfg.same_surface_distance)])
        for k in range(surface.max() + 1):
            chosen = inlier & (surface[local] == k)
            frames_seen = len(np.unique(seg.frame[segments[surface == k]]))
            if not _seen_enough(seg.frame[seg.ids[cells[chosen]]], seg.cells_per_frame, cfg):
                continue
            planes.append(_Plane(normal=normal[g], offset=_weighted_median(offset, weight * (surface == k)),
                                 points=members[chosen], frames=frames_seen, groups=[int(g)]))
    return planes, num_groups, scales


def fit_planes(frames: Frames, pelvis_path: np.ndarray | None = None, cfg: PlaneFitConfig = PlaneFitConfig(),
               progress: bool = True) -> PlaneFit:
    """Fit box primitives to the planar surfaces of a metric, gravity-aligned depth video.

    Args:
        frames: depth video in metres, z up, floor at z = 0, person pixels removed (depth 0).
        pelvis_path: optional (N, 3) pelvis positions of the person (world frame); points farther
            than ``cfg.pelvis_radius`` from the path are ignored.
        cfg: thresholds (:class:`PlaneFitConfig`).
        progress: show a progress bar over the frames.

    Returns:
        A :class:`PlaneFit`; ``boxes`` is empty when no planar surface passed the filters.
    """
    if not isinstance(frames, Frames):
        raise ValueError(f"frames must be a crisp_gym.reconstruct.frames.Frames, got {type(frames).__name__}")
    if not isinstance(cfg, PlaneFitConfig):
        raise ValueError(f"cfg must be a PlaneFitConfig, got {type(cfg).__name__}")
    start = time.perf_counter()
    tree = None if pelvis_path is None else _pelvis_tree(pelvis_path)
    rng = np.random.default_rng(cfg.seed)
    timings = {"segment": 0.0, "associate": 0.0}
    dropped = {"depth_percentile": 0, "pelvis": 0}
    # Many small K-means fits: OpenMP's thread start-up costs more than the fits themselves.
    with threadpool_limits(limits=1, user_api="openmp"):
        seg = _segment_video(frames, tree, cfg, rng, timings, dropped, progress)
    tic = time.perf_counter()
    planes, num_groups, scales = _group_planes(seg, frames.cam_c2w[:, :3, 3], cfg, rng)
    yaw = _dominant_yaw(planes, cfg)
    planes = _merge_planes(_snap_yaw(planes, yaw, cfg), cfg)
    timings["planes"] = time.perf_counter() - tic
    tic = time.perf_counter()
    boxes, infos = [], []
    for plane in planes:
        plane_boxes, fill = _plane_boxes(plane, yaw, cfg)
        if not plane_boxes:
            continue
        boxes += plane_boxes
        infos.append(PlaneInfo(normal=plane.normal, offset=plane.offset, points=len(plane.points),
                               frames=plane.frames, groups=tuple(plane.groups), fill_ratio=fill,
                               boxes=len(plane_boxes)))
    timings["boxes"] = time.perf_counter() - tic
    timings["total"] = time.perf_counter() - start
    return PlaneFit(boxes=boxes, planes=infos, timings=timings, segments=len(seg.frame), groups=num_groups,
                    frame_scales=scales, dropped=dropped)
