"""Synthetic depth videos with ground truth: what a monocular front end (MegaSAM) would hand us.

A box scene and the humanoid moving in it (a clip of :mod:`crisp_gym.synth.clips`, a registered clip,
or a random one with background boxes) are ray-cast from a moving, handheld-like camera into
depth, a simply shaded RGB image and person masks. The depth then gets the errors of a
monocular depth network (:class:`~crisp_gym.synth.depth_noise.DepthNoise`): one unknown global scale (depth *and* camera
translations are divided by it, so the input is consistently scaled as MegaSAM's is), a smooth
per-frame scale drift, a low-frequency distortion, per-pixel noise growing with depth, flying
pixels at depth edges and optional holes. Camera poses are given in the first camera's frame,
as MegaSAM gives them.

Camera views (:data:`~crisp_gym.synth.camera.VIEWS`, :mod:`crisp_gym.synth.camera`):

* ``orbit``: a handheld camera beside the person, following them with a lag, slowly orbiting
  and dollying, with a little shake;
* ``low``: the camera in front of the person, its eye below the top of every raised support
  (e.g. a seat), so those tops are never visible: the occluded-support case of contact-guided
  completion;
* ``upper_body``: the camera frames the person's upper body, pitched so that every raised
  support top stays below the image for the whole clip: the off-frame support case.

:func:`render_synth_video` renders a :class:`SynthSpec`; :func:`crisp_gym.synth.truth.write_synth_input`
writes it:

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

``crisp synth --kind KIND --seed S -o DIR`` is the command line (:mod:`crisp_gym.synth.video_cli`); :func:`benchmark_suite` and
:func:`occluded_suite` are the fixed sets the benchmarks use.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from crisp_gym.geometry import intrinsic_from_fov, pixel_rays
from crisp_gym.humanoid import BODY_NAMES, HumanoidConfig, build_humanoid
from crisp_gym.metrics import box_signed_distance, support_tops
from crisp_gym.motion import Motion
from crisp_gym.reconstruct.body_mesh import BodyMesher
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.raycast import box_mesh
from crisp_gym.registry import load_clip
from crisp_gym.scene import Box
from crisp_gym.synth.camera import VIEWS, CameraConfig, camera_path, motion_heading
from crisp_gym.synth.clips import KINDS, make_clip
from crisp_gym.synth.depth_noise import DepthNoise, NoiseModel

VIDEO_KINDS: tuple[str, ...] = (*KINDS, "random")
"""Scene kinds: those of :func:`crisp_gym.synth.clips.make_clip`, and ``random`` (one of the kinds with
raised supports, chosen by the seed, with background boxes)."""


_RANDOM_KINDS = ("stairs_up", "stairs_down", "platform_step", "chair_sit")
_FLOOR_TOP_COS = 0.9  # a hit normal this close to +z is on a box's top face
_LIGHT = np.array([0.35, -0.25, 1.0]) / np.linalg.norm([0.35, -0.25, 1.0])
_SKY = np.array([0.72, 0.80, 0.92])
_SKIN = np.array([0.86, 0.62, 0.48])
_PALETTE = np.array([[0.56, 0.56, 0.52], [0.45, 0.60, 0.80], [0.80, 0.55, 0.35], [0.55, 0.75, 0.50],
                     [0.75, 0.50, 0.70], [0.85, 0.80, 0.45], [0.50, 0.70, 0.75]])


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


def _fit_length(motion: Motion, frames: int) -> Motion:
    """The first ``frames`` frames, holding the last pose when the motion is shorter."""
    if frames <= motion.num_frames:
        return motion.slice(0, frames)
    index = np.minimum(np.arange(frames), motion.num_frames - 1)
    return replace(motion, root_pos=motion.root_pos[index], root_quat=motion.root_quat[index],
                   dof_pos=motion.dof_pos[index], contacts=None if motion.contacts is None else motion.contacts[index])




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
    boxes = boxes + _distractors(rng, count, side, motion, motion_heading(motion))
    width, height = cfg.width, cfg.height
    intrinsic = intrinsic_from_fov(width, height, cfg.camera.fov(spec.view))
    poses = camera_path(motion, boxes, spec.view, rng, intrinsic, width, height, cfg.camera, side)
    noise = NoiseModel(cfg.noise, rng, motion.num_frames, motion.fps, width, height)

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
        "source": "synthetic-video", "generator": "crisp_gym.synth.video.render_synth_video",
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
