"""Support surfaces from a sparse point cloud in the floor frame: the ground, seats, level tops.

Structure from motion gives a few thousand points, not a depth map per frame, so the per-frame
segmentation of :mod:`crisp_gym.reconstruct.planes` has nothing to work on; and outdoors the points of
vegetation and of a sloping bank fill every height. What a tracked humanoid needs from such a
scene is where it can stand and sit, so three kinds of box are made, each 5 cm thick under its
top as in the dense path:

* the **ground**: one box at z = 0 under the floor's points and the person's path;
* **seats** (:func:`seat_surface`), guided by contact as in the paper: under a body part the
  motion rests on, the highest level layer of points below it, at its densest, is the surface it
  rests on (a low log's top, with its sides and the ground under it);
* other **level tops** (:func:`level_tops`) only where the points say so plainly: a dense layer
  with few points above it (a table top or a step, not a slice through a bush or a slope).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from sklearn.cluster import DBSCAN

from crisp_gym.geometry import min_area_rectangle
from crisp_gym.scene import Box


@dataclass(frozen=True)
class SparsePlaneConfig:
    """Settings of the sparse surfaces (metres).

    Attributes:
        radius: points farther than this horizontally from the pelvis path are ignored.
        max_height: points higher than this are ignored (nothing above it is stood or sat on).
        layer_thickness: a surface's points lie within ± half this of its height.
        min_points: points a level top needs.
        seat_min_points: points a seat's layer needs (a seat is looked for only under a contact).
        seat_min_side: a seat's footprint is at least this wide (a contact patch is a few points).
        max_above_share: a level top has at most this share of its point count above it.
        min_area: m², the smallest level top.
        min_height: level tops lower than this are part of the ground.
        patch_gap: points closer than this horizontally belong to the same patch.
        thickness: box thickness under the top face.
        margin: footprints are grown by this on each side.
    """

    radius: float = 2.5
    max_height: float = 1.5
    layer_thickness: float = 0.05
    min_points: int = 40
    seat_min_points: int = 10
    seat_min_side: float = 0.6
    max_above_share: float = 0.2
    min_area: float = 0.1
    min_height: float = 0.08
    patch_gap: float = 0.15
    thickness: float = 0.05
    margin: float = 0.05


def _level_box(xy: np.ndarray, top: float, cfg: SparsePlaneConfig, name: str) -> Box:
    """A box whose top is level at ``top`` over the minimum-area rectangle of ``xy`` (grown by the margin)."""
    rectangle = min_area_rectangle(xy)
    rotation = np.eye(3)
    rotation[:2, :2] = rectangle.axes.T
    half = np.array([*(rectangle.half_size + cfg.margin), cfg.thickness / 2])
    return Box(center=np.array([*rectangle.centre, top - cfg.thickness / 2]), rotation=rotation, half_size=half,
               source="planar", name=name)


def _near_path(points: np.ndarray, pelvis_path: np.ndarray, cfg: SparsePlaneConfig) -> np.ndarray:
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    near = cKDTree(np.asarray(pelvis_path)[:, :2]).query(points[:, :2])[0] <= cfg.radius
    return points[near & (points[:, 2] <= cfg.max_height)]


def ground_box(points: np.ndarray, pelvis_path: np.ndarray, config: SparsePlaneConfig | None = None) -> Box:
    """The ground at z = 0 under the floor's points near the path and under the path itself."""
    cfg = config or SparsePlaneConfig()
    points = _near_path(points, pelvis_path, cfg)
    floor = points[np.abs(points[:, 2]) <= cfg.layer_thickness / 2, :2]
    return _level_box(np.concatenate([floor, np.asarray(pelvis_path)[:, :2]]), 0.0, cfg, "ground")


def _densest_layer(z: np.ndarray, thickness: float) -> tuple[float, int]:
    """Median height and count of the densest window of ``thickness`` among sorted heights ``z``."""
    lo = np.searchsorted(z, z - thickness / 2)
    hi = np.searchsorted(z, z + thickness / 2, side="right")
    best = int(np.argmax(hi - lo))
    return float(np.median(z[lo[best]:hi[best]])), int(hi[best] - lo[best])


def seat_surface(points: np.ndarray, patch: np.ndarray, max_drop: float,
                 config: SparsePlaneConfig | None = None) -> Box | None:
    """The level surface a body resting with contact ``patch`` ((K, 3) points) sits on, or ``None``.

    The points under the patch's footprint and at most ``max_drop`` below its lowest part are
    scanned from the top down for the first layer with enough points: the top of what is under
    the body (its sides and the ground below come later in the scan). The top is then the densest
    layer within one layer's thickness below that first one: the first layer is met at the upper
    edge of the surface's noise (on the bundled real video, 4-5 cm above the log's densest layer).
    """
    cfg = config or SparsePlaneConfig()
    patch = np.asarray(patch, dtype=float).reshape(-1, 3)
    low = float(np.quantile(patch[:, 2], 0.1))
    rectangle = min_area_rectangle(patch[:, :2])
    local = (np.asarray(points)[:, :2] - rectangle.centre) @ rectangle.axes.T
    inside = np.all(np.abs(local) <= np.maximum(rectangle.half_size + cfg.margin, cfg.seat_min_side / 2), axis=1)
    column = np.asarray(points)[inside]
    column = column[(column[:, 2] <= low + cfg.layer_thickness) & (column[:, 2] >= low - max_drop)]
    z = np.sort(column[:, 2])[::-1]
    for top in z:  # from the highest point down: the first well-populated layer
        layer = column[np.abs(column[:, 2] - (top - cfg.layer_thickness / 2)) <= cfg.layer_thickness / 2]
        if len(layer) >= cfg.seat_min_points:
            below = z[(z <= top) & (z >= top - 2 * cfg.layer_thickness)][::-1]
            height, _ = _densest_layer(below, cfg.layer_thickness)
            layer = column[np.abs(column[:, 2] - height) <= cfg.layer_thickness / 2]
            return _level_box(np.concatenate([layer[:, :2], patch[:, :2]]), height, cfg, "seat")
    return None


def level_tops(points: np.ndarray, pelvis_path: np.ndarray, config: SparsePlaneConfig | None = None) -> list[Box]:
    """Level surfaces above the ground that the points show plainly (see the module docstring)."""
    cfg = config or SparsePlaneConfig()
    points = _near_path(points, pelvis_path, cfg)
    points = points[points[:, 2] >= cfg.min_height - cfg.layer_thickness / 2]
    boxes: list[Box] = []
    remaining = np.sort(points[:, 2])
    while len(remaining) >= cfg.min_points:
        height, count = _densest_layer(remaining, cfg.layer_thickness)
        if count < cfg.min_points:
            break
        remaining = remaining[np.abs(remaining - height) > cfg.layer_thickness / 2]
        if height < cfg.min_height:
            continue
        layer = points[np.abs(points[:, 2] - height) <= cfg.layer_thickness / 2]
        labels = DBSCAN(eps=cfg.patch_gap, min_samples=5).fit_predict(layer[:, :2])
        for label in set(labels) - {-1}:
            patch = layer[labels == label]
            if len(patch) < cfg.min_points:
                continue
            box = _level_box(patch[:, :2], height, cfg, f"top_{len(boxes)}")
            if 4 * box.half_size[0] * box.half_size[1] < cfg.min_area:
                continue
            local = (points - box.center) @ box.rotation
            above = points[:, 2] > height + cfg.layer_thickness / 2
            over = np.all(np.abs(local[:, :2]) <= box.half_size[:2], axis=1) & above
            if over.sum() <= cfg.max_above_share * len(patch):
                boxes.append(box)
    return boxes
