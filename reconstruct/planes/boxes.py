"""Stage 4, per plane: the inliers' footprint on an occupancy grid, its minimum-area rectangle,
guillotine cuts where a notch is missing, and boxes of the paper's thickness behind each piece."""

from __future__ import annotations

import heapq

import cv2
import numpy as np

from crisp_gym.geometry import min_area_rectangle, plane_axes
from crisp_gym.reconstruct.planes.config import PlaneFitConfig
from crisp_gym.reconstruct.planes.surfaces import Plane, footprint_cells, wrap_quarter
from crisp_gym.scene import Box


def _occupancy(ab: np.ndarray, cfg: PlaneFitConfig) -> tuple[np.ndarray, np.ndarray]:
    """Occupancy grid of 2D points, closed (far and grazing surfaces are sampled sparsely) and
    cleaned of specks; and each point's cell in it, (-1, -1) for points in removed specks."""
    pad = round(cfg.footprint_closing / cfg.footprint_cell)
    cells = footprint_cells(ab, cfg.footprint_cell)
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


def boxes_of_plane(plane: Plane, yaw: float | None, cfg: PlaneFitConfig) -> tuple[list[Box], float]:
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
            off = wrap_quarter(angle - yaw)
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
