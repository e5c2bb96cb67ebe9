"""Geometry shared by reconstruction and the synthetic data: pinhole cameras and pixel rays, planes
(least squares, RANSAC, snapping to gravity, in-plane axes) and minimum-area rectangles.

Conventions: OpenCV cameras (x right, y down, z forward, pixel centres at integer u, v); a world
with z up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

_Z = np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------- cameras


def pixel_rays(intrinsic: np.ndarray, width: int, height: int, u0: int = 0, v0: int = 0) -> np.ndarray:
    """(H, W, 3) camera-frame ray directions with unit z of the pixels ``u0 <= u < width``,
    ``v0 <= v < height`` (pixel centres at integer u, v, as OpenCV): a pixel's point is ``depth * ray``."""
    u, v = np.meshgrid(np.arange(u0, width, dtype=np.float64), np.arange(v0, height, dtype=np.float64))
    return np.stack([(u - intrinsic[0, 2]) / intrinsic[0, 0], (v - intrinsic[1, 2]) / intrinsic[1, 1],
                     np.ones_like(u)], axis=-1)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = _Z) -> np.ndarray:
    """(4, 4) camera → world pose of an OpenCV camera at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: the view direction is parallel to `up`")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1)
    pose[:3, 3] = eye
    return pose


def intrinsic_from_fov(width: int, height: int, fov_x_deg: float) -> np.ndarray:
    """(3, 3) pinhole K with square pixels and the principal point at the image centre."""
    f = 0.5 * width / np.tan(0.5 * np.radians(fov_x_deg))
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------- planes


def fit_plane(points: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane (unit normal along ``up``, offset: ``normal · p + offset = 0``) through ``points``."""
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][-1]
    normal = normal if normal @ up >= 0 else -normal
    return normal, float(-normal @ centre)


def ransac_plane(points: np.ndarray, up: np.ndarray, min_cos: float, threshold: float, iterations: int,
                 rng: np.random.Generator, refinements: int = 2) -> tuple[np.ndarray, float, np.ndarray] | None:
    """The plane (unit normal along ``up``, offset, inlier mask within ``threshold``) with the most
    inliers among ``iterations`` hypotheses whose normal has at least ``min_cos`` with ``up``,
    refitted by least squares on its inliers ``refinements`` times; ``None`` when no hypothesis
    qualifies.

    Written out rather than Open3D's ``segment_plane`` because that one draws from a global seed.
    """
    if len(points) < 3:
        return None
    sample = points[rng.integers(len(points), size=(iterations, 3))]
    normals = np.cross(sample[:, 1] - sample[:, 0], sample[:, 2] - sample[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-9
    normals[ok] /= norms[ok, None]
    normals *= np.where(normals @ up < 0, -1.0, 1.0)[:, None]
    ok &= normals @ up >= min_cos
    if not ok.any():
        return None
    normals, offsets = normals[ok], -np.einsum("ij,ij->i", normals[ok], sample[ok, 0])
    counts = (np.abs(points @ normals.T + offsets) < threshold).sum(axis=0)
    best = int(np.argmax(counts))
    normal, offset = normals[best], offsets[best]
    for _ in range(refinements):  # refit on the inliers, then take the inliers of the refit
        inliers = np.abs(points @ normal + offset) < threshold
        if inliers.sum() < 3:
            return None
        normal, offset = fit_plane(points[inliers], up)
    return normal, offset, np.abs(points @ normal + offset) < threshold


def ransac_height_plane(points: np.ndarray, hint: np.ndarray, threshold: float,
                        seed: int) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC plane through ``points`` with its normal on ``hint``'s side: (unit normal, inlier mask).

    Unlike :func:`ransac_plane`, the offset along ``hint`` is regressed on the two in-plane
    coordinates (scikit-learn's ``RANSACRegressor``), which needs at most a slope and stays
    well-posed for a thin strip of points, such as the few contacts under a foot.
    """
    from sklearn.linear_model import LinearRegression, RANSACRegressor  # noqa: PLC0415 - only this fit uses it

    frame = plane_frame(hint)
    local = points @ frame
    ransac = RANSACRegressor(LinearRegression(), min_samples=3, residual_threshold=threshold, random_state=seed)
    ransac.fit(local[:, :2], local[:, 2])
    a, b = ransac.estimator_.coef_
    normal = frame @ np.array([-a, -b, 1.0])
    normal /= np.linalg.norm(normal)
    return normal, ransac.inlier_mask_


def snap_to_gravity(normal: np.ndarray, snap_deg: float) -> np.ndarray:
    """A unit ``normal`` made exactly vertical (a level surface) or horizontal (a plumb one) when
    within ``snap_deg`` of it, else unchanged (z-up, gravity-aligned input)."""
    if abs(normal[2]) >= math.cos(math.radians(snap_deg)):
        return np.array([0.0, 0.0, math.copysign(1.0, normal[2])])
    if abs(normal[2]) <= math.sin(math.radians(snap_deg)):
        flat = np.array([normal[0], normal[1], 0.0])
        return flat / np.linalg.norm(flat)
    return normal


def plane_axes(normal: np.ndarray) -> np.ndarray:
    """(2, 3) in-plane unit axes u, v of a unit ``normal`` with u × v = normal; u horizontal unless
    the plane is level (then u = +x)."""
    u = np.cross(_Z, normal)
    if np.linalg.norm(u) < 1e-6:
        u = np.array([1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(normal, u)])


def plane_frame(normal: np.ndarray) -> np.ndarray:
    """(3, 3) right-handed frame with columns u, v, ``normal`` (u, v from :func:`plane_axes`)."""
    u, v = plane_axes(normal)
    return np.stack([u, v, normal], axis=1)


# --------------------------------------------------------------------------- rectangles


@dataclass(frozen=True)
class Rectangle:
    """A rectangle in the plane.

    Attributes:
        centre: (2,).
        axes: (2, 2) rows: unit directions of its sides (the second turned +90° from the first).
        half_size: (2,) half extents along ``axes``.
        corners: (4, 2) in order around it (``corners[1] - corners[0]`` along its second side).
    """

    centre: np.ndarray
    axes: np.ndarray
    half_size: np.ndarray
    corners: np.ndarray


def min_area_rectangle(xy: np.ndarray) -> Rectangle:
    """The minimum-area rectangle around 2D points (OpenCV's rotating calipers, in float32; a
    zero width for collinear points)."""
    (cx, cy), (w, h), angle = rect = cv2.minAreaRect(np.asarray(xy, dtype=np.float32))
    yaw = np.deg2rad(angle)
    axes = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
    return Rectangle(np.array([cx, cy]), axes, np.array([w / 2, h / 2]), cv2.boxPoints(rect))
