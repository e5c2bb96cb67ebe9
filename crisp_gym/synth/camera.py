"""Camera paths of the synthetic videos: a handheld orbit, a low view below every raised support top,
and an upper-body view that keeps the supports out of the image."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from crisp_gym.geometry import look_at
from crisp_gym.humanoid import build_humanoid
from crisp_gym.motion import Motion, foot_sole_heights
from crisp_gym.scene import Box

VIEWS: tuple[str, ...] = ("orbit", "low", "upper_body")
"""Camera views, see the module docstring."""


@dataclass(frozen=True)
class CameraConfig:
    """How the virtual camera moves.

    Attributes:
        fov_x_deg: horizontal field of view (degrees).
        distance: range of the horizontal distance from the person (m), orbit and upper_body.
        height: range of the eye height above the person's support level (m), orbit and upper_body.
        azimuth_deg: range of the camera's angle around the person from their walking direction,
            to either side (degrees), orbit and upper_body.
        orbit_deg: amplitude of the slow orbit around the person (degrees).
        dolly: amplitude of the slow change of distance (m).
        follow_seconds: lag of the camera operator: the followed target is the pelvis path
            smoothed over this time (s).
        shake_m: handheld position jitter, standard deviation (m).
        shake_deg: handheld rotation jitter, standard deviation (degrees).
        shake_seconds: time scale of the jitter (s).
        low_distance: distance range of the low view (m).
        low_azimuth_deg: azimuth range of the low view around the person's facing (degrees).
        low_eye: the low view's eye is this far below the lowest raised support top (m range);
            it never goes below min_eye.
        min_eye: lowest eye height above the floor (m).
        upper_fov_x_deg: horizontal field of view of the upper_body view (degrees): zoomed in on the person.
        upper_distance: distance range of the upper_body view (m).
        upper_height: eye height range of the upper_body view above the person's support level (m).
        upper_margin_deg: in the upper_body view, raised support tops stay at least this far
            below the image's bottom edge (degrees).
    """

    fov_x_deg: float = 60.0
    distance: tuple[float, float] = (3.2, 4.4)
    height: tuple[float, float] = (1.5, 2.0)
    azimuth_deg: tuple[float, float] = (55.0, 125.0)
    orbit_deg: float = 20.0
    dolly: float = 0.3
    follow_seconds: float = 0.6
    shake_m: float = 0.01
    shake_deg: float = 0.4
    shake_seconds: float = 0.25
    low_distance: tuple[float, float] = (2.6, 3.4)
    low_azimuth_deg: tuple[float, float] = (-45.0, 45.0)
    low_eye: tuple[float, float] = (0.10, 0.20)
    min_eye: float = 0.12
    upper_fov_x_deg: float = 45.0
    upper_distance: tuple[float, float] = (2.2, 3.0)
    upper_height: tuple[float, float] = (1.2, 1.5)
    upper_margin_deg: float = 2.5

    def fov(self, view: str) -> float:
        """Horizontal field of view of ``view`` (degrees)."""
        return self.upper_fov_x_deg if view == "upper_body" else self.fov_x_deg


def smooth_noise(rng: np.random.Generator, n: int, dims: int, sigma: float) -> np.ndarray:
    """(n, dims) Gaussian-smoothed white noise with unit standard deviation."""
    sigma = max(sigma, 1e-3)
    pad = int(4 * sigma) + 1
    raw = rng.standard_normal((n + 2 * pad, dims))
    smooth = gaussian_filter1d(raw, sigma, axis=0)[pad:pad + n]
    return smooth * np.sqrt(2.0 * np.sqrt(np.pi) * sigma)  # white noise smoothed by σ has std (2√π σ)^-½


def _look(eye: np.ndarray, target: np.ndarray, shake: np.ndarray) -> np.ndarray:
    """(T, 4, 4) poses looking from ``eye`` at ``target``, rotated by ``shake`` (T, 3) rotvecs
    in the camera frame."""
    poses = np.stack([look_at(e, t) for e, t in zip(eye, target)])
    poses[:, :3, :3] = poses[:, :3, :3] @ Rotation.from_rotvec(shake).as_matrix()
    return poses


def _raised_tops(boxes: list[Box]) -> list[np.ndarray]:
    """(P, 3) points covering the top face of each box other than the floor (edges included)."""
    tops = []
    grid = np.stack(np.meshgrid(np.linspace(-1, 1, 9), np.linspace(-1, 1, 9)), -1).reshape(-1, 2)
    for box in boxes:
        if box.name == "floor":
            continue
        axis = int(np.argmax(np.abs(box.rotation[2])))  # the box axis closest to vertical
        u, v = [a for a in range(3) if a != axis]
        local = np.zeros((len(grid), 3))
        local[:, u] = grid[:, 0] * box.half_size[u]
        local[:, v] = grid[:, 1] * box.half_size[v]
        local[:, axis] = np.sign(box.rotation[2, axis]) * box.half_size[axis]
        tops.append(box.center + local @ box.rotation.T)
    return tops


def motion_heading(motion: Motion) -> float:
    """The walking direction (rad): the net pelvis displacement, or the first frame's facing."""
    disp = motion.root_pos[-1, :2] - motion.root_pos[0, :2]
    if np.linalg.norm(disp) > 0.3:
        return float(np.arctan2(disp[1], disp[0]))
    facing = Rotation.from_quat(motion.root_quat[0], scalar_first=True).apply([1.0, 0.0, 0.0])
    return float(np.arctan2(facing[1], facing[0]))


def camera_path(motion: Motion, boxes: list[Box], view: str, rng: np.random.Generator,
                intrinsic: np.ndarray, width: int, height: int,
                config: CameraConfig | None = None, side: float = 1.0) -> np.ndarray:
    """(T, 4, 4) camera → world poses (OpenCV) following ``motion`` in the ``view`` style.

    ``side`` (±1) is the side of the walking direction the ``orbit``/``upper_body`` camera stays on.
    """
    cfg = config or CameraConfig()
    if view not in VIEWS:
        raise ValueError(f"unknown view {view!r}; expected one of {VIEWS}")
    n, fps = motion.num_frames, motion.fps
    t = np.arange(n) / fps
    pelvis = gaussian_filter1d(motion.root_pos, cfg.follow_seconds * fps, axis=0, mode="nearest")
    level = gaussian_filter1d(foot_sole_heights(motion, build_humanoid()), 2 * cfg.follow_seconds * fps,
                              mode="nearest")
    psi = motion_heading(motion)
    shake_pos = smooth_noise(rng, n, 3, cfg.shake_seconds * fps) * cfg.shake_m
    shake_rot = smooth_noise(rng, n, 3, cfg.shake_seconds * fps) * np.radians(cfg.shake_deg)
    orbit = np.radians(cfg.orbit_deg) * np.sin(2 * np.pi * t / rng.uniform(6.0, 10.0) + rng.uniform(0, 2 * np.pi))
    dolly = cfg.dolly * np.sin(2 * np.pi * t / rng.uniform(5.0, 9.0) + rng.uniform(0, 2 * np.pi))
    if view == "low":
        azimuth = psi + np.radians(rng.uniform(*cfg.low_azimuth_deg)) + 0.5 * orbit
        distance = rng.uniform(*cfg.low_distance) + 0.5 * dolly
        raised = [pts[:, 2].min() for pts in _raised_tops(boxes)]
        top = min(raised) if raised else 0.5
        eye_z = np.full(n, max(cfg.min_eye, top - rng.uniform(*cfg.low_eye)))
        shake_pos[:, 2] = np.minimum(shake_pos[:, 2], 0.0)  # never lift the eye towards the tops
    else:
        upper = view == "upper_body"
        azimuth = psi + side * np.radians(rng.uniform(*cfg.azimuth_deg)) + orbit
        distance = rng.uniform(*(cfg.upper_distance if upper else cfg.distance)) + dolly
        eye_z = level + rng.uniform(*(cfg.upper_height if upper else cfg.height))
    eye = np.c_[pelvis[:, :2] + distance[:, None] * np.c_[np.cos(azimuth), np.sin(azimuth)], eye_z] + shake_pos
    target = np.c_[pelvis[:, :2], pelvis[:, 2] - 0.1]
    if view != "upper_body":
        return _look(eye, target, shake_rot)
    # Upper body: the yaw follows the person, the pitch is the lowest (constant) one that keeps
    # every raised top below the image's bottom edge in every frame.
    tops = np.concatenate(_raised_tops(boxes)) if len(boxes) > 1 else np.zeros((0, 3))
    horizontal = target[:, :2] - eye[:, :2]
    horizontal /= np.linalg.norm(horizontal, axis=1, keepdims=True)
    half_fov_v = np.arctan(0.5 * height / intrinsic[1, 1])
    for pitch in np.radians(np.arange(-25.0, 35.0, 0.25)):
        look = eye + np.c_[horizontal * np.cos(pitch), np.full(n, np.sin(pitch))]
        poses = _look(eye, look, shake_rot)
        if len(tops) == 0:
            return poses
        cam = np.einsum("tji,tpj->tpi", poses[:, :3, :3], tops[None] - poses[:, None, :3, 3])
        front = cam[..., 2] > 0.05
        # angle of each top point below the optical axis, in the vertical image plane
        below = np.arctan2(cam[..., 1], cam[..., 2])
        hidden = ~front | (below > half_fov_v + np.radians(cfg.upper_margin_deg))
        if hidden.all():
            return poses
    raise RuntimeError("no camera pitch keeps the raised supports below the upper-body view")
