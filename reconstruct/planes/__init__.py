"""Planar fitting: a metric, gravity-aligned depth video → box primitives (paper Sec. 3.2 and its
appendix "Details of planar fitting"), made fast.

The stages, each vectorised with numpy/OpenCV:

1. **Per frame** (:mod:`~crisp_gym.reconstruct.planes.segments`), on a coarse grid: the pointmap is block-averaged (this is the smoothing: a block
   of r×r pixels averages r² depth samples), points beyond the frame's depth percentile and far
   from the pelvis path are dropped, normals come from finite differences over a few cells, cells
   on creases and depth edges (where the pointmap is not locally flat) get none, K-means on the
   normals (fit on a subsample, every cell assigned to its nearest centre; centres closer than a
   few degrees merged) labels orientations, and connected components of each orientation on the
   image grid are the frame's planar segments; small ones are dropped.
2. **Across frames** (:mod:`~crisp_gym.reconstruct.planes.association`): the cells of each segment are reprojected into a few earlier frames with the
   camera poses; where the reprojected depth agrees with what that frame saw, the segment under it
   overlaps. Segments that overlap enough, whose normals agree and whose planes coincide are
   linked; connected components of the link graph (union-find) are the global planar groups.
3. **Per group** (:mod:`~crisp_gym.reconstruct.planes.surfaces`): a RANSAC plane normal, snapped to gravity when within a few degrees of vertical
   or horizontal. Monocular depth drifts in scale from frame to frame, so each frame's depth is
   then rescaled (about its camera) to put its segments on the planes the whole video agrees on;
   the segments' planes that chain together are one surface (a group that chained two parallel
   surfaces a step apart gives both), its inliers the cells near their own segment's plane.
   Vertical planes close to the scene's dominant yaw are turned onto it, and coplanar planes that
   touch are merged.
4. **Per plane** (:mod:`~crisp_gym.reconstruct.planes.boxes`): the inliers' footprint on an occupancy grid, its minimum-area rectangle (edges
   horizontal and vertical for vertical surfaces), split into rectangles by guillotine cuts where
   a notch is missing from it, and a box of the paper's 0.05 m thickness *behind* each rectangle
   (away from the cameras), so its visible face is where the points are. The floor is one box.

Input: :class:`~crisp_gym.reconstruct.frames.Frames` already metric, gravity-aligned (z up, floor at z = 0)
with person pixels removed (depth 0), and optionally the pelvis path (N, 3) of the person.

Every threshold is a field of :class:`~crisp_gym.reconstruct.planes.config.PlaneFitConfig`;
:func:`fit_planes` runs the stages.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.planes.association import Seen, associate
from crisp_gym.reconstruct.planes.boxes import boxes_of_plane
from crisp_gym.reconstruct.planes.config import PlaneFit, PlaneFitConfig, PlaneInfo
from crisp_gym.reconstruct.planes.segments import (
    block_stride,
    frame_grid,
    grid_normals,
    grow_segments,
    orientation_labels,
    planar_segments,
)
from crisp_gym.reconstruct.planes.surfaces import (
    Plane,
    dominant_yaw,
    merge_planes,
    ransac_normal,
    snap_yaw,
    weighted_median,
)

__all__ = ["PlaneFit", "PlaneFitConfig", "PlaneInfo", "fit_planes"]


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
class Segmented:
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
                   timings: dict[str, float], dropped: dict[str, int], progress: bool) -> Segmented:
    """Stages 1 and 2: per-frame segments, and their links to the segments of earlier frames."""
    stride = block_stride(frames.image_size[1], cfg)
    rays = frames.rays().astype(np.float32)
    seg_frame, seg_size, seg_normal, seg_centroid, links = [], [], [], [], []
    cell_points, cell_ids = [], []
    recent: dict[int, Seen] = {}
    total = 0
    for t in tqdm(range(frames.num_frames), desc="planes: frames", unit="frame", disable=not progress):
        tic = time.perf_counter()
        pose = frames.cam_c2w[t]
        grid = frame_grid(frames, t, rays, stride, cfg, tree, dropped)
        normals, has = grid_normals(grid, pose[:3, 3].astype(np.float32), cfg)
        segments, count = planar_segments(orientation_labels(normals, has, cfg, rng), cfg)
        segments = grow_segments(segments, count, grid, normals, has, cfg)
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
                    links.append(associate(cell_points[-1], cell_ids[-1], recent[t - k], frames.intrinsic, stride,
                                            *known, cfg))
        recent[t] = Seen(segments=np.where(labelled, segments + total, -1), depth=grid.depth,
                          world_to_cam=np.linalg.inv(pose))
        recent.pop(t - max(cfg.association_offsets), None)
        total += count
        timings["associate"] += time.perf_counter() - tic
    return Segmented(frame=np.concatenate(seg_frame), size=np.concatenate(seg_size),
                      normal=np.concatenate(seg_normal), centroid=np.concatenate(seg_centroid), points=np.concatenate(cell_points).astype(np.float64),
                      ids=np.concatenate(cell_ids),
                      links=np.concatenate(links) if links else np.zeros((0, 2), dtype=np.int64),
                      cells_per_frame=int(grid.depth.size))


def _frame_scales(seg: Segmented, group_of: np.ndarray, normal: np.ndarray, fitted: np.ndarray,
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
            target[g] = weighted_median(offset[mine], weight[mine])
        wanted = (target[group] - np.einsum("ij,ij->i", n, cam)) / np.where(steady, reach, 1.0)
        for t in np.unique(frame[steady]):
            mine = steady & (frame == t)
            scales[t] = weighted_median(wanted[mine], weight[mine])
    return np.clip(scales, 1 - cfg.frame_scale_correction, 1 + cfg.frame_scale_correction)


def _seen_enough(cell_frames: np.ndarray, cells_per_frame: int, cfg: PlaneFitConfig) -> bool:
    """A group or surface whose inlier cells were seen in frames ``cell_frames`` is kept: enough
    cells, and seen in enough frames or well in one."""
    if len(cell_frames) < cfg.min_group_points:
        return False
    per_frame = np.unique(cell_frames, return_counts=True)[1]
    return len(per_frame) >= cfg.min_group_frames or per_frame.max() >= cfg.single_view_share * cells_per_frame


def _group_planes(seg: Segmented, cameras: np.ndarray, cfg: PlaneFitConfig,
                  rng: np.random.Generator) -> tuple[list[Plane], int, np.ndarray]:
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
        normal[g] = ransac_normal(seg.points[cells], prior, cfg, rng)
        fitted[g] = True
    scales = _frame_scales(seg, group_of, normal, fitted, cameras, cfg)
    cell_frame = seg.frame[seg.ids]
    points = cameras[cell_frame] + scales[cell_frame, None] * (seg.points - cameras[cell_frame])
    planes = []
    for g in np.flatnonzero(fitted):
        cells = order[bounds[g]:bounds[g + 1]]
        members = points[cells]
        if cfg.frame_scale_correction > 0:  # drift spread the raw points: RANSAC again on corrected ones
            normal[g] = ransac_normal(members, normal[g], cfg, rng)
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
            planes.append(Plane(normal=normal[g], offset=weighted_median(offset, weight * (surface == k)),
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
    yaw = dominant_yaw(planes, cfg)
    planes = merge_planes(snap_yaw(planes, yaw, cfg), cfg)
    timings["planes"] = time.perf_counter() - tic
    tic = time.perf_counter()
    boxes, infos = [], []
    for plane in planes:
        plane_boxes, fill = boxes_of_plane(plane, yaw, cfg)
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
