"""The settings of planar fitting (:class:`PlaneFitConfig`, one flat set of fields: they are the
``crisp reconstruct`` flags) and what it returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from crisp_gym.scene import Box


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
