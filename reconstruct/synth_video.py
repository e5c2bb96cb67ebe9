"""Synthetic depth videos with ground truth: what a monocular front end (MegaSAM) would hand us.

A box scene and the humanoid moving in it (a clip of :mod:`crisp_gym.reconstruct.synth`, a registered clip,
or a random one with background boxes) are ray-cast from a moving, handheld-like camera into
depth, a simply shaded RGB image and person masks. The depth then gets the errors of a
monocular depth network (:class:`DepthNoise`): one unknown global scale (depth *and* camera
translations are divided by it, so the input is consistently scaled as MegaSAM's is), a smooth
per-frame scale drift, a low-frequency distortion, per-pixel noise growing with depth, flying
pixels at depth edges and optional holes. Camera poses are given in the first camera's frame,
as MegaSAM gives them.

Camera views (:data:`VIEWS`):

* ``orbit``: a handheld camera beside the person, following them with a lag, slowly orbiting
  and dollying, with a little shake;
* ``low``: the camera in front of the person, its eye below the top of every raised support
  (e.g. a seat), so those tops are never visible: the occluded-support case of contact-guided
  completion;
* ``upper_body``: the camera frames the person's upper body, pitched so that every raised
  support top stays below the image for the whole clip: the off-frame support case.

:func:`render_synth_video` renders a :class:`SynthSpec`; :func:`write_synth_input` writes it:

``input.npz``
    the reconstruction input (``depths`` float16, ``intrinsic``, ``cam_c2w``, ``images``,
    ``masks`` (person = 1), ``fps``), see :mod:`crisp_gym.reconstruct.io`.
``motion_camera.npz``
    the motion as GVHMR-style SMPL parameters in each frame's camera frame
    (:func:`crisp_gym.reconstruct.io.save_camera_smpl`), for ``--motion``.
``gt/``
    a clip directory (``scene.xml``, ``primitives.json``, ``motion.npz`` with contacts,
    ``meta.json`` with the scale, the spec, the configs, the visibility of every box's top)
    plus ``cameras.npz`` (true metric ``cam_c2w``, ``world_from_input``, ``scale``,
    ``intrinsic``) and ``contacts.npz`` (``frame``, ``body``, ``point``, ``prob``: world-frame
    contact points of the ground-truth contacts).

``crisp synth --kind KIND --seed S -o DIR`` is the command line; :func:`benchmark_suite` and
:func:`occluded_suite` are the fixed sets the benchmarks use.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import open3d as o3d
import tyro
from scipy.ndimage import gaussian_filter1d, maximum_filter, minimum_filter, zoom
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from crisp_gym.atomic import atomic_directory
from crisp_gym.clip import write_clip
from crisp_gym.humanoid import BODY_NAMES, HumanoidConfig, build_humanoid
from crisp_gym.metrics import box_signed_distance, support_tops
from crisp_gym.motion import Motion, foot_sole_heights
from crisp_gym.registry import load_clip
from crisp_gym.scene import Box, load_primitives
from crisp_gym.reconstruct.body_mesh import BodyMesher, pixel_rays
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.io import save_camera_smpl
from crisp_gym.reconstruct.raycast import box_mesh, intrinsic_from_fov, look_at
from crisp_gym.reconstruct.synth import KINDS, make_clip

VIEWS: tuple[str, ...] = ("orbit", "low", "upper_body")
"""Camera views, see the module docstring."""

VIDEO_KINDS: tuple[str, ...] = (*KINDS, "random")
"""Scene kinds: those of :func:`crisp_gym.reconstruct.synth.make_clip`, and ``random`` (one of the kinds with
raised supports, chosen by the seed, with background boxes)."""

_RANDOM_KINDS = ("stairs_up", "stairs_down", "platform_step", "chair_sit")
_FLOOR_TOP_COS = 0.9  # a hit normal this close to +z is on a box's top face
_LIGHT = np.array([0.35, -0.25, 1.0]) / np.linalg.norm([0.35, -0.25, 1.0])
_SKY = np.array([0.72, 0.80, 0.92])
_SKIN = np.array([0.86, 0.62, 0.48])
_PALETTE = np.array([[0.56, 0.56, 0.52], [0.45, 0.60, 0.80], [0.80, 0.55, 0.35], [0.55, 0.75, 0.50],
                     [0.75, 0.50, 0.70], [0.85, 0.80, 0.45], [0.50, 0.70, 0.75]])


@dataclass(frozen=True)
class DepthNoise:
    """Errors of a monocular depth network (applied in this order).

    Attributes:
        scale_range: the unknown global scale ``s`` is drawn log-uniformly from this range; the
            input depth and camera translations are the true ones divided by ``s`` (metric = s × input).
        scale_drift: standard deviation over the clip of the smooth per-frame scale error
            (relative; its mean over the clip is 0, so ``s`` stays the clip's true scale).
        drift_seconds: time scale of that drift (s).
        distortion: RMS of a low-frequency multiplicative distortion of each depth map (relative).
        distortion_seconds: period over which the distortion pattern changes (s).
        pixel_noise: per-pixel Gaussian noise, σ = ``pixel_noise`` × depth² (1/m): it grows with depth.
        flying_pixels: probability that a pixel at a depth edge takes a depth between the
            foreground and the background (a "flying pixel").
        edge_jump: a relative depth jump within ``edge_width`` pixels that counts as an edge.
        edge_width: how many pixels from an edge flying pixels reach.
        holes: fraction of pixels lost in blob-shaped holes (depth 0).
        float16: store depth as float16, as MegaSAM does.
    """

    scale_range: tuple[float, float] = (0.5, 2.0)
    scale_drift: float = 0.02
    drift_seconds: float = 1.0
    distortion: float = 0.01
    distortion_seconds: float = 4.0
    pixel_noise: float = 0.001
    flying_pixels: float = 0.5
    edge_jump: float = 0.05
    edge_width: int = 1
    holes: float = 0.0
    float16: bool = True

    def __post_init__(self) -> None:
        lo, hi = self.scale_range
        if not 0 < lo <= hi:
            raise ValueError(f"scale_range must be 0 < low <= high, got {self.scale_range}")
        for name in ("scale_drift", "distortion", "pixel_noise", "edge_jump"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.flying_pixels <= 1 or not 0 <= self.holes < 1:
            raise ValueError(f"flying_pixels must be in [0, 1] and holes in [0, 1), got "
                             f"{self.flying_pixels}, {self.holes}")
        if self.edge_width < 1 or self.drift_seconds <= 0 or self.distortion_seconds <= 0:
            raise ValueError("edge_width, drift_seconds and distortion_seconds must be positive")

    @classmethod
    def clean(cls) -> DepthNoise:
        """Exact metric depth: no scale, drift, distortion, noise, flying pixels or holes."""
        return cls(scale_range=(1.0, 1.0), scale_drift=0.0, distortion=0.0, pixel_noise=0.0,
                   flying_pixels=0.0, holes=0.0, float16=False)


@dataclass(frozen=True)
class CameraConfig:
    """How the virtual camera moves.

    Attributes:
        fov_x_deg: horizontal field of view (degrees).
        distance: range of the horizontal distance from the person (m), ``orbit`` and ``upper_body``.
        height: range of the eye height above the person's support level (m), ``orbit`` and ``upper_body``.
        azimuth_deg: range of the camera's angle around the person from their walking direction,
            to either side (degrees), ``orbit`` and ``upper_body``.
        orbit_deg: amplitude of the slow orbit around the person (degrees).
        dolly: amplitude of the slow change of distance (m).
        follow_seconds: lag of the camera operator: the followed target is the pelvis path
            smoothed over this time (s).
        shake_m: handheld position jitter, standard deviation (m).
        shake_deg: handheld rotation jitter, standard deviation (degrees).
        shake_seconds: time scale of the jitter (s).
        low_distance: distance range of the ``low`` view (m).
        low_azimuth_deg: azimuth range of the ``low`` view around the person's facing (degrees).
        low_eye: the ``low`` view's eye is this far below the lowest raised support top (m range);
            it never goes below ``min_eye``.
        min_eye: lowest eye height above the floor (m).
        upper_fov_x_deg: horizontal field of view of the ``upper_body`` view (degrees): zoomed in on the person.
        upper_distance: distance range of the ``upper_body`` view (m).
        upper_height: eye height range of the ``upper_body`` view above the person's support level (m).
        upper_margin_deg: in the ``upper_body`` view, raised support tops stay at least this far
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


@dataclass(frozen=True)
class SynthVideoConfig:
    """What to render.

    Attributes:
        width, height: image size (pixels).
        frames: number of frames; ``None`` is the motion's length. Fewer frames cut the motion,
            more hold its last pose while the camera keeps moving.
        noise: the depth errors.
        camera: the camera motion.
    """

    width: int = 512
    height: int = 384
    frames: int | None = None
    noise: DepthNoise = field(default_factory=DepthNoise)
    camera: CameraConfig = field(default_factory=CameraConfig)

    def __post_init__(self) -> None:
        if self.width < 8 or self.height < 8:
            raise ValueError(f"image size must be at least 8x8, got {self.width}x{self.height}")
        if self.frames is not None and self.frames < 2:
            raise ValueError(f"frames must be at least 2, got {self.frames}")


@dataclass(frozen=True)
class SynthSpec:
    """One synthetic video.

    Attributes:
        kind: one of :data:`VIDEO_KINDS` (ignored when ``clip`` is given).
        seed: makes the scene, the motion, the camera and the noise reproducible.
        view: one of :data:`VIEWS`.
        distractors: background boxes (a wall and blocks) placed away from the path, on the far
            side from the camera; ``random`` adds 1-3 when this is 0.
        clip: render this registered clip (name or directory) instead of generating one.
    """

    kind: str
    seed: int
    view: str = "orbit"
    distractors: int = 0
    clip: str | None = None

    def __post_init__(self) -> None:
        if self.clip is None and self.kind not in VIDEO_KINDS:
            raise ValueError(f"unknown kind {self.kind!r}; expected one of {VIDEO_KINDS}")
        if self.view not in VIEWS:
            raise ValueError(f"unknown view {self.view!r}; expected one of {VIEWS}")
        if self.distractors < 0:
            raise ValueError(f"distractors must be >= 0, got {self.distractors}")

    @property
    def name(self) -> str:
        source = Path(self.clip).name if self.clip else self.kind
        return f"{source}_{self.view}_s{self.seed}"


def benchmark_suite(seeds=range(10)) -> list[SynthSpec]:
    """The fixed benchmark set: stairs up and down, platforms and seats in turn, each with
    background boxes, seen by the ``orbit`` camera (10 seeds by default)."""
    kinds = ("stairs_up", "platform_step", "chair_sit", "stairs_down")
    return [SynthSpec(kinds[i % len(kinds)], int(seed), "orbit", distractors=2) for i, seed in enumerate(seeds)]


def occluded_suite(seeds=range(6)) -> list[SynthSpec]:
    """The occluded-support set: a seat below the ``low`` camera's eye and a platform below the
    ``upper_body`` camera's view, in turn (6 seeds by default)."""
    cases = (("chair_sit", "low"), ("platform_step", "upper_body"))
    return [SynthSpec(cases[i % 2][0], int(seed), cases[i % 2][1]) for i, seed in enumerate(seeds)]


@dataclass(frozen=True)
class SynthVideo:
    """A rendered synthetic video and its ground truth.

    Attributes:
        frames: the reconstruction input: noisy depth up to the scale, camera poses in the first
            camera's frame with translations divided by the scale, RGB, person masks.
        boxes: the true scene (world: z up, floor top at z = 0).
        motion: the true motion in the world, with ground-truth contacts.
        motion_camera: the same motion in each frame's camera frame (OpenCV axes, metres).
        cam_c2w: (T, 4, 4) true metric camera → world poses.
        scale: metric = ``scale`` × input.
        contacts: ground-truth contact points: ``frame`` (M,), ``body`` (M,), ``point`` (M, 3) world.
        top_visible_pixels: (B,) pixels, over all frames, where each box's top face is seen.
        visible_pixels: (B,) pixels, over all frames, where any face of each box is seen.
        meta: provenance and settings (JSON-ready).
    """

    frames: Frames
    boxes: list[Box]
    motion: Motion
    motion_camera: Motion
    cam_c2w: np.ndarray
    scale: float
    contacts: dict[str, np.ndarray]
    top_visible_pixels: np.ndarray
    visible_pixels: np.ndarray
    meta: dict

    @property
    def world_from_input(self) -> np.ndarray:
        """(4, 4) rigid map from the input's frame, scaled to metres, to the true world."""
        first = self.frames.cam_c2w[0].copy()
        first[:3, 3] *= self.scale
        return self.cam_c2w[0] @ np.linalg.inv(first)


# --------------------------------------------------------------------------- scene and motion


def _fit_length(motion: Motion, frames: int) -> Motion:
    """The first ``frames`` frames, holding the last pose when the motion is shorter."""
    if frames <= motion.num_frames:
        return motion.slice(0, frames)
    index = np.minimum(np.arange(frames), motion.num_frames - 1)
    return replace(motion, root_pos=motion.root_pos[index], root_quat=motion.root_quat[index],
                   dof_pos=motion.dof_pos[index], contacts=None if motion.contacts is None else motion.contacts[index])


def _heading(motion: Motion) -> float:
    """The walking direction (rad): the net pelvis displacement, or the first frame's facing."""
    disp = motion.root_pos[-1, :2] - motion.root_pos[0, :2]
    if np.linalg.norm(disp) > 0.3:
        return float(np.arctan2(disp[1], disp[0]))
    facing = Rotation.from_quat(motion.root_quat[0], scalar_first=True).apply([1.0, 0.0, 0.0])
    return float(np.arctan2(facing[1], facing[0]))


def _distractors(rng: np.random.Generator, count: int, side: float, motion: Motion, psi: float) -> list[Box]:
    """A wall and ``count - 1`` blocks beside the path, on the side away from the camera (``-side``)."""
    forward = np.array([np.cos(psi), np.sin(psi), 0.0])
    left = np.array([-np.sin(psi), np.cos(psi), 0.0])
    rotation = Rotation.from_euler("z", psi).as_matrix()
    along = motion.root_pos[:, :2] @ forward[:2]
    lateral = float(np.mean(motion.root_pos[:, :2] @ left[:2]))
    start, end = along.min(), along.max()
    boxes: list[Box] = []
    far = 1.2  # the person's arms reach about 0.6 m from the path; stairs and seats up to 0.7 m
    footprints: list[tuple[float, float]] = []
    for i in range(count - 1):
        half = np.array([rng.uniform(0.2, 0.5), rng.uniform(0.2, 0.4), rng.uniform(0.2, 0.5)])
        for _ in range(20):  # a place along the path that no other block takes
            s = rng.uniform(start - 0.5, end + 0.5)
            if all(abs(s - s2) > half[0] + h2 + 0.2 for s2, h2 in footprints):
                break
        else:
            continue
        footprints.append((s, half[0]))
        offset = 1.0 + half[1] + rng.uniform(0.0, 0.3)
        far = max(far, offset + half[1])
        center = s * forward + (lateral - side * offset) * left + [0.0, 0.0, half[2]]
        boxes.append(Box(center=center, rotation=rotation, half_size=half, name=f"block_{i}"))
    if count > 0:
        height = rng.uniform(2.2, 2.8)
        offset = far + rng.uniform(0.3, 0.8) + 0.05
        half = np.array([(end - start) / 2 + 2.5, 0.05, height / 2])
        center = (start + end) / 2 * forward + (lateral - side * offset) * left + [0.0, 0.0, height / 2]
        boxes.append(Box(center=center, rotation=rotation, half_size=half, name="wall"))
    return boxes


# --------------------------------------------------------------------------- camera path


def _smooth_noise(rng: np.random.Generator, n: int, dims: int, sigma: float) -> np.ndarray:
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
    psi = _heading(motion)
    shake_pos = _smooth_noise(rng, n, 3, cfg.shake_seconds * fps) * cfg.shake_m
    shake_rot = _smooth_noise(rng, n, 3, cfg.shake_seconds * fps) * np.radians(cfg.shake_deg)
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


# --------------------------------------------------------------------------- depth errors


@dataclass
class _NoiseModel:
    """Per-clip draws of :class:`DepthNoise`, applied frame by frame."""

    cfg: DepthNoise
    rng: np.random.Generator
    num_frames: int
    fps: float
    width: int
    height: int

    def __post_init__(self) -> None:
        lo, hi = self.cfg.scale_range
        self.scale = float(np.exp(self.rng.uniform(np.log(lo), np.log(hi))))
        drift = _smooth_noise(self.rng, self.num_frames, 1, self.cfg.drift_seconds * self.fps)[:, 0]
        drift -= drift.mean()  # the clip's mean scale is the true one
        spread = drift.std()  # normalised over the clip: a short clip drifts as much as a long one
        self.drift = 1.0 + self.cfg.scale_drift * (drift / spread if spread > 1e-12 else drift)
        terms = 4
        self._freq = self.rng.uniform(-1.0, 1.0, (terms, 2))  # cycles per image
        self._phase = self.rng.uniform(0, 2 * np.pi, terms)
        self._omega = 2 * np.pi / self.cfg.distortion_seconds * self.rng.uniform(0.5, 1.5, terms)
        self._amp = self.cfg.distortion / np.sqrt(terms / 2) * self.rng.choice([-1.0, 1.0], terms)
        self._u = np.arange(self.width) / self.width
        self._v = np.arange(self.height) / self.height

    def apply(self, depth: np.ndarray, k: int) -> np.ndarray:
        """Frame ``k``'s true metric depth (0 = no hit) → its noisy depth divided by the scale."""
        cfg, rng = self.cfg, self.rng
        valid = depth > 0
        d = depth.astype(np.float32) * np.float32(self.drift[k])
        if cfg.distortion > 0:
            # Σ amp cos(a_k(v) + b_k(u)) = Σ amp (cos a cos b − sin a sin b): separable rank-2 terms
            a = 2 * np.pi * np.outer(self._v, self._freq[:, 1]) + self._phase + self._omega * k / self.fps
            b = 2 * np.pi * np.outer(self._freq[:, 0], self._u)
            rows = np.concatenate([self._amp * np.cos(a), -self._amp * np.sin(a)], axis=1).astype(np.float32)
            cols = np.concatenate([np.cos(b), np.sin(b)], axis=0).astype(np.float32)
            d *= 1.0 + np.einsum("hk,kw->hw", rows, cols)
        if cfg.flying_pixels > 0:
            size = 2 * cfg.edge_width + 1
            lo = minimum_filter(np.where(valid, d, np.inf), size)
            hi = maximum_filter(np.where(valid, d, 0.0), size)
            edge = valid & np.isfinite(lo) & (hi - lo > cfg.edge_jump * lo)
            fly = edge & (rng.random(d.shape, dtype=np.float32) < cfg.flying_pixels)
            d[fly] = lo[fly] + rng.random(int(fly.sum()), dtype=np.float32) * (hi[fly] - lo[fly])
        if cfg.pixel_noise > 0:
            d += rng.standard_normal(d.shape, dtype=np.float32) * np.float32(cfg.pixel_noise) * d * d
        d = np.where(valid & (d > 0), d, 0.0)
        if cfg.holes > 0:
            coarse = rng.standard_normal((self.height // 16 + 2, self.width // 16 + 2))
            blobs = zoom(coarse, (self.height / coarse.shape[0], self.width / coarse.shape[1]), order=1)
            blobs = blobs[:self.height, :self.width]
            d[blobs < np.quantile(blobs, cfg.holes)] = 0.0
        return d / np.float32(self.scale)


# --------------------------------------------------------------------------- rendering


def render_synth_video(spec: SynthSpec, config: SynthVideoConfig | None = None,
                       progress: bool = True) -> SynthVideo:
    """Render ``spec`` (deterministic for its seed); see the module docstring."""
    cfg = config or SynthVideoConfig()
    rng = np.random.default_rng([int(spec.seed), VIEWS.index(spec.view), 20250])
    if spec.clip is not None:
        clip = load_clip(spec.clip)
        boxes, motion, clip_meta = list(clip.boxes), clip.motion, dict(clip.meta)
        kind = str(clip_meta.get("kind", "clip"))
    else:
        kind = spec.kind if spec.kind != "random" else _RANDOM_KINDS[int(rng.integers(len(_RANDOM_KINDS)))]
        boxes, motion, clip_meta = make_clip(kind, spec.seed)
    motion = _fit_length(motion, cfg.frames or motion.num_frames)
    side = float(rng.choice([-1.0, 1.0]))
    count = spec.distractors or (int(rng.integers(1, 4)) if spec.kind == "random" and spec.clip is None else 0)
    boxes = boxes + _distractors(rng, count, side, motion, _heading(motion))
    width, height = cfg.width, cfg.height
    intrinsic = intrinsic_from_fov(width, height, cfg.camera.fov(spec.view))
    poses = camera_path(motion, boxes, spec.view, rng, intrinsic, width, height, cfg.camera, side)
    noise = _NoiseModel(cfg.noise, rng, motion.num_frames, motion.fps, width, height)

    start = time.perf_counter()
    n = motion.num_frames
    depth = np.zeros((n, height, width), np.float16 if cfg.noise.float16 else np.float32)
    rgb = np.zeros((n, height, width, 3), np.uint8)
    mask = np.zeros((n, height, width), bool)
    top_visible = np.zeros(len(boxes), np.int64)
    visible = np.zeros(len(boxes), np.int64)
    height_m = float(clip_meta.get("humanoid_height", 1.70))
    mesher = BodyMesher(build_humanoid(HumanoidConfig(height=height_m)))
    # The boxes as Open3D tensors once; each frame casts one scene of them plus the posed humanoid
    # (geometry id len(boxes)). Rebuilding a scene of a few hundred triangles costs microseconds,
    # and one cast of every ray measured faster than a cast at a kept static scene plus another
    # at the humanoid alone.
    static = [(o3d.core.Tensor(np.asarray(m.vertices, np.float32)), o3d.core.Tensor(np.asarray(m.faces, np.uint32)))
              for m in map(box_mesh, boxes)]
    body_faces = o3d.core.Tensor(mesher.faces.astype(np.uint32))
    albedo = np.vstack([_PALETTE[[0 if b.name == "floor" else 1 + i % (len(_PALETTE) - 1)]]
                        for i, b in enumerate(boxes)] + [_SKIN[None], _SKY[None]]).astype(np.float32)
    rays = pixel_rays(intrinsic, width, height).astype(np.float32)
    ray_buffer = np.empty((height, width, 6), np.float32)  # origins | directions, reused every frame
    qpos = motion.qpos()
    contact_frame, contact_body, contact_point = [], [], []
    stage = {"raycast": 0.0, "noise": 0.0, "shading": 0.0}  # seconds per stage, for the benchmarks
    for k in tqdm(range(n), desc="render", unit="frame", disable=not progress):
        rot, eye = poses[k, :3, :3].astype(np.float32), poses[k, :3, 3].astype(np.float32)
        ray_buffer[..., :3] = eye
        np.einsum("hwj,ij->hwi", rays, rot, out=ray_buffer[..., 3:])  # camera z = 1: t_hit is z-depth
        clock = time.perf_counter()
        vertices = mesher.pose(qpos[k])
        scene = o3d.t.geometry.RaycastingScene()
        for box_vertices, box_faces in static:
            scene.add_triangles(box_vertices, box_faces)
        scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), body_faces)
        hit = scene.cast_rays(o3d.core.Tensor.from_numpy(ray_buffer))
        t_hit = hit["t_hit"].numpy()
        ids = hit["geometry_ids"].numpy().astype(np.int64)
        missed = ~np.isfinite(t_hit)
        ids[missed] = -1
        true_depth = np.where(missed, np.float32(0.0), t_hit)
        normal = hit["primitive_normals"].numpy()
        stage["raycast"] += time.perf_counter() - clock
        person = ids == len(boxes)
        on_box = (ids >= 0) & (ids < len(boxes))
        visible += np.bincount(ids[on_box], minlength=len(boxes))
        top_visible += np.bincount(ids[on_box & (normal[..., 2] > _FLOOR_TOP_COS)], minlength=len(boxes))
        mask[k] = person
        clock = time.perf_counter()
        depth[k] = noise.apply(true_depth, k)
        stage["noise"] += time.perf_counter() - clock
        clock = time.perf_counter()
        rgb[k] = _shade(ids, normal, eye + true_depth[..., None] * ray_buffer[..., 3:], albedo, person)
        stage["shading"] += time.perf_counter() - clock
        if motion.contacts is not None:
            for b in np.flatnonzero(motion.contacts[k]):
                contact_frame.append(k)
                contact_body.append(BODY_NAMES[b])
                contact_point.append(_contact_point(vertices[mesher.body_of_vertex == b], boxes))
    render_seconds = time.perf_counter() - start

    cam0_inv = np.linalg.inv(poses[0])
    input_poses = np.einsum("ij,tjk->tik", cam0_inv, poses)
    input_poses[:, :3, 3] /= noise.scale
    frames = Frames(depth=depth, intrinsic=intrinsic, cam_c2w=input_poses, fps=motion.fps, rgb=rgb, person_mask=mask)
    person_pixels = mask.reshape(n, -1).sum(axis=1)
    meta = {
        "source": "synthetic-video", "generator": "crisp_gym.reconstruct.synth_video.render_synth_video",
        "name": spec.name, "spec": asdict(spec), "kind": kind, "scale": noise.scale,
        "image_size": [width, height], "fps": motion.fps, "num_frames": n,
        "config": asdict(cfg), "clip_meta": clip_meta, "render_seconds": render_seconds,
        "render_seconds_by_stage": stage,
        "boxes": [{"name": b.name or f"box_{i}", "top_visible_pixels": int(top_visible[i]),
                   "visible_pixels": int(visible[i])} for i, b in enumerate(boxes)],
        "person_pixels": {"min": int(person_pixels.min()), "median": float(np.median(person_pixels)),
                          "frames_without_person": int((person_pixels == 0).sum())},
    }
    contacts = {"frame": np.asarray(contact_frame, np.int64), "body": np.asarray(contact_body, dtype=str),
                "point": np.asarray(contact_point, np.float64).reshape(-1, 3)}
    return SynthVideo(frames=frames, boxes=boxes, motion=motion, motion_camera=_in_cameras(motion, poses),
                      cam_c2w=poses, scale=noise.scale, contacts=contacts, top_visible_pixels=top_visible,
                      visible_pixels=visible, meta=meta)


def _contact_point(vertices: np.ndarray, boxes: list[Box], tolerance: float = 0.01) -> np.ndarray:
    """Where a body rests on the scene: the middle of its vertices nearest the boxes, dropped onto
    the highest support top below them."""
    distance = box_signed_distance(vertices, boxes)
    near = vertices[distance <= distance.min() + tolerance]
    centre = near.mean(axis=0)
    tops = support_tops(centre[None, :2], boxes)[0]
    below = tops[tops <= near[:, 2].min() + tolerance]
    return np.r_[centre[:2], below.max()] if below.size else centre


def _shade(ids: np.ndarray, normal: np.ndarray, points: np.ndarray, albedo: np.ndarray,
           person: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: Lambert-shaded albedo with a 0.25 m 3D checker on the boxes (texture for
    photometric odometry) and the sky where nothing is hit (id -1)."""
    colour = albedo[ids]  # id -1 (nothing hit) is the last row: the sky
    light = 0.35 + 0.65 * np.clip(normal @ _LIGHT.astype(np.float32), 0.0, 1.0)
    cells = np.floor(points * np.float32(4.0)).astype(np.int32).sum(axis=-1) & 1
    light *= np.where(person | (ids < 0), np.float32(1.0), np.float32(0.8) + np.float32(0.2) * cells)
    light[ids < 0] = 1.0
    return (np.minimum(colour * light[..., None], 1.0) * 255.0 + 0.5).astype(np.uint8)


def _in_cameras(motion: Motion, poses: np.ndarray) -> Motion:
    """``motion`` with frame k expressed in camera k's frame."""
    rot_wc = np.swapaxes(poses[:, :3, :3], 1, 2)
    root_pos = np.einsum("tij,tj->ti", rot_wc, motion.root_pos - poses[:, :3, 3])
    root = Rotation.from_matrix(rot_wc) * Rotation.from_quat(motion.root_quat, scalar_first=True)
    return replace(motion, root_pos=root_pos, root_quat=root.as_quat(scalar_first=True), contacts=None)


# --------------------------------------------------------------------------- files


def write_synth_input(directory: str | Path, video: SynthVideo, overwrite: bool = False) -> Path:
    """Write ``video`` as ``input.npz``, ``motion_camera.npz`` and ``gt/`` (see the module docstring).

    The directory is built under a temporary name and renamed into place, so an interrupted
    write never leaves a half-written input.
    """
    directory = Path(directory)
    with atomic_directory(directory, overwrite) as tmp:
        frames = video.frames
        float16 = bool(video.meta.get("config", {}).get("noise", {}).get("float16", False))
        with open(tmp / "input.npz", "wb") as f:
            np.savez_compressed(f, depths=frames.depth.astype(np.float16 if float16 else np.float32),
                                intrinsic=frames.intrinsic, cam_c2w=frames.cam_c2w, images=frames.rgb,
                                masks=frames.person_mask.astype(np.uint8), fps=np.float64(frames.fps))
        save_camera_smpl(video.motion_camera, tmp / "motion_camera.npz")
        gt = write_clip(tmp / "gt", video.boxes, video.motion, video.meta)
        np.savez(gt / "cameras.npz", cam_c2w=video.cam_c2w, world_from_input=video.world_from_input,
                 scale=np.float64(video.scale), intrinsic=frames.intrinsic)
        np.savez(gt / "contacts.npz", frame=video.contacts["frame"], body=video.contacts["body"],
                 point=video.contacts["point"], prob=np.ones(len(video.contacts["frame"])))
    return directory


@dataclass(frozen=True)
class SynthTruth:
    """The ground truth of a written synthetic input (``gt/``).

    Attributes:
        boxes: the true scene; motion: the true world motion with contacts.
        cam_c2w: (T, 4, 4) true metric camera poses.
        world_from_input: (4, 4) rigid map from the metric-scaled input frame to the world.
        scale: metric = scale × input.
        contacts: ``frame``, ``body``, ``point``, ``prob`` arrays of ``contacts.npz``.
        meta: ``meta.json``.
    """

    boxes: list[Box]
    motion: Motion
    cam_c2w: np.ndarray
    world_from_input: np.ndarray
    scale: float
    contacts: dict[str, np.ndarray]
    meta: dict


def load_ground_truth(directory: str | Path) -> SynthTruth:
    """Read the ``gt/`` of a directory written by :func:`write_synth_input` (or ``gt/`` itself)."""
    directory = Path(directory)
    gt = directory / "gt" if (directory / "gt").is_dir() else directory
    files = ("primitives.json", "motion.npz", "meta.json", "cameras.npz", "contacts.npz")
    missing = [f for f in files if not (gt / f).is_file()]
    if missing:
        raise FileNotFoundError(f"{gt} is not a synthetic ground truth: missing {missing} (expected {list(files)})")
    with np.load(gt / "cameras.npz") as cams, np.load(gt / "contacts.npz") as contacts:
        return SynthTruth(boxes=load_primitives(gt / "primitives.json"), motion=Motion.load(gt / "motion.npz"),
                          cam_c2w=cams["cam_c2w"], world_from_input=cams["world_from_input"],
                          scale=float(cams["scale"]), contacts={k: contacts[k] for k in contacts.files},
                          meta=json.loads((gt / "meta.json").read_text()))


def alignment_errors(scale: float, world_from_input: np.ndarray, truth: SynthTruth | SynthVideo) -> dict[str, float]:
    """How far an estimated alignment (metric = ``scale`` × input, then the rigid
    ``world_from_input``) is from the truth.

    ``scale_error`` is relative; ``gravity_error_deg`` is the angle between the estimated and
    the true up direction; ``floor_error_m`` / ``floor_error_max_m`` are the mean / largest
    height, in the estimated world, of the true floor under the person's pelvis path (0 when the
    estimated floor is the true one there).
    """
    aligned_from_true = np.asarray(world_from_input) @ np.diag([*(np.full(3, scale / truth.scale)), 1.0]) \
        @ np.linalg.inv(truth.world_from_input)
    true_up = aligned_from_true[:3, :3] @ [0.0, 0.0, 1.0]
    gravity = np.degrees(np.arccos(np.clip(true_up[2] / np.linalg.norm(true_up), -1.0, 1.0)))
    floor = np.c_[truth.motion.root_pos[:, :2], np.zeros(truth.motion.num_frames)]
    heights = np.abs(floor @ aligned_from_true[:3, :3].T + aligned_from_true[:3, 3])[:, 2]
    return {"scale_error": float(scale / truth.scale - 1.0), "gravity_error_deg": float(gravity),
            "floor_error_m": float(heights.mean()), "floor_error_max_m": float(heights.max())}


# --------------------------------------------------------------------------- command line


@dataclass(frozen=True)
class SynthArgs:
    """Render a synthetic depth video of a person in a box scene, with its ground truth."""

    output: Annotated[Path, tyro.conf.arg(aliases=["-o"])]
    """Directory to write (input.npz, motion_camera.npz, gt/)."""
    kind: Literal["flat_walk", "stairs_up", "stairs_down", "platform_step", "chair_sit", "random"] = "random"
    """Scene kind (random: stairs, a platform or a seat with background boxes)."""
    seed: int = 0
    """Seed of the scene, motion, camera and noise."""
    view: Literal["orbit", "low", "upper_body"] = "orbit"
    """Camera view: orbit, low (raised tops never visible), upper_body (supports off-frame)."""
    frames: int | None = None
    """Number of frames (default: the motion's length)."""
    size: str = "512x384"
    """Image size WIDTHxHEIGHT."""
    distractors: int = 0
    """Background boxes (a wall and blocks) beside the path."""
    clip: str | None = None
    """Render this registered clip (name or directory) instead of generating a scene."""
    clean: bool = False
    """Exact metric depth (no scale, drift, distortion, noise, flying pixels or holes)."""
    noise: DepthNoise = field(default_factory=DepthNoise)
    camera: CameraConfig = field(default_factory=CameraConfig)
    overwrite: bool = False
    """Replace an existing output directory."""


def _parse_size(size: str) -> tuple[int, int]:
    try:
        width, height = (int(x) for x in size.lower().split("x"))
    except ValueError:
        raise ValueError(f"size must be WIDTHxHEIGHT (e.g. 512x384), got {size!r}") from None
    return width, height


def main(argv: list[str] | None = None) -> int:
    """``crisp synth``: render and write a synthetic input."""
    args = tyro.cli(SynthArgs, args=argv, prog="crisp synth")
    width, height = _parse_size(args.size)
    config = SynthVideoConfig(width=width, height=height, frames=args.frames,
                              noise=DepthNoise.clean() if args.clean else args.noise, camera=args.camera)
    spec = SynthSpec(args.kind, args.seed, args.view, args.distractors, args.clip)
    if args.output.exists() and not args.overwrite:
        raise FileExistsError(f"{args.output} exists; pass --overwrite to replace it")
    video = render_synth_video(spec, config)
    out = write_synth_input(args.output, video, overwrite=args.overwrite)
    hidden = [b["name"] for b in video.meta["boxes"] if b["top_visible_pixels"] == 0]
    print(f"wrote {spec.name}: {video.frames.num_frames} frames {width}x{height} in "
          f"{video.meta['render_seconds']:.1f} s, scale {video.scale:.3f}, boxes never seen from above: "
          f"{hidden or 'none'} -> {out}")
    return 0
