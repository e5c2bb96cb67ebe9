"""Alignment: remove the person, recover the metric scale from them, find gravity and put the floor at z = 0.

A monocular front end (MegaSAM) gives depth and camera poses up to one unknown scale, in the
first camera's frame; an HMR method (GVHMR) gives the person in metres in each camera's frame.
:func:`align` turns both into the world the simulator needs:

1. **person removal**: the person mask, dilated (flying pixels hug the silhouette), becomes
   missing depth, so the person is never fitted as scene;
2. **metric scale** (the paper's Sec. 3.1): the motion's humanoid is rendered into each camera;
   per frame, the median ratio of its depth to the video's depth over the person's pixels (the
   mask eroded, away from edges) is that frame's scale; frames whose scale is more than a few
   MADs from the median are dropped and the median of the rest is the scale;
3. **gravity**: the person's up direction (pelvis → head, averaged over the motion) is a prior
   that picks the floor among the points near the person's path: among the large planes whose
   normal is within a tolerance of it (seeded RANSAC on the points with such normals, one plane
   after another), the lowest. It is then refitted frame by frame (a monocular depth map's
   scale errs per frame, moving that frame's floor) and combined: the mean normal is gravity's
   up, the median offset the floor. Without a motion the prior is the cameras' image-up and the
   search is near the cameras' path;
4. **floor at z = 0**: the world's z axis is that normal, its origin the floor point under the
   first frame's pelvis (or under the first camera), its x axis the first camera's view
   direction along the floor. Where the floor near the person was rarely in view, or only
   metres away, the person's feet, which touch it, set its height instead.

The result is the aligned :class:`Frames` (metres, person removed), the motion in the world,
and an :class:`Alignment` record with the diagnostics.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d
from scipy.ndimage import gaussian_filter1d, maximum_filter, minimum_filter
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from crisp_gym.geometry import fit_plane, plane_axes, ransac_plane
from crisp_gym.humanoid import BODY_NAMES, HumanoidConfig, build_humanoid
from crisp_gym.motion import Motion, compute_kinematics, foot_sole_heights
from crisp_gym.reconstruct.body_mesh import BodyMesher, cast_mesh
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.io import MotionInput


@dataclass(frozen=True)
class AlignConfig:
    """Settings of :func:`align`.

    Attributes:
        mask_dilation_px: the person mask is grown by this many pixels before its depth is removed.
        mask_erosion_px: the mask is shrunk by this many pixels where the scale is measured, away
            from the silhouette's mixed depths.
        min_person_pixels: frames with fewer measurable person pixels do not vote for the scale.
        scale_frames: at most this many frames (evenly spread over those with a person) vote.
        mad_threshold: per-frame scales farther than this many robust standard deviations
            (1.4826 × MAD) from the median are outliers.
        drift_seconds: when > 0, the per-frame scales (outliers dropped, interpolated between the
            voting frames, Gaussian-smoothed over this many seconds) also correct each frame's
            depth by its ratio to the clip's scale: a monocular depth network's scale drifts
            from frame to frame, and the person measures that drift where it matters. The
            camera translations keep the one clip-wide scale. 0 keeps a single scale.
        camera0_iterations: at most this many fixed-point iterations of the scale for a motion
            given in the first camera's frame (placing it in later cameras needs the scale).
        human_height: stature of the humanoid rendered for the scale (m); the scale is only as
            right as this (the paper's cue: a typical human's size is known).
        floor_frames: frames (evenly spread) whose points are searched for the floor.
        floor_pixel_stride: pixel step when taking those points.
        floor_depth_percentile: a frame's points beyond this percentile of its depth (the noisiest) are dropped.
        floor_radius: only points this close to the person's pelvis path are searched (m): the
            floor that matters is the one under the person, and far depth is the least reliable.
        camera_floor_radius: ... to the camera path, when there is no motion (m).
        voxel_size: the floor search's point spacing (m).
        normal_radius: neighbourhood of the point normals (m).
        up_tolerance_deg: the floor's normal lies within this angle of the person's up direction.
        camera_up_tolerance_deg: ... of the cameras' image-up when there is no motion (cameras tilt).
        plane_threshold: RANSAC inlier distance (m).
        floor_band: each frame's floor is refitted from its points this close to the joint fit (m):
            a per-frame depth scale error moves a frame's floor by a few cm.
        min_frame_floor_points: a frame needs this many floor points to refit it.
        ransac_iterations: plane hypotheses per RANSAC.
        max_planes: horizontal planes extracted, one after another.
        floor_min_fraction: a plane is "large" with at least this fraction of the largest
            horizontal plane's points; the floor is the lowest large plane.
        min_floor_points: a plane needs at least this many points.
        floor_seen_fraction: when the floor near the person is refitted in fewer than this
            fraction of the searched frames (it was barely seen where the person walks: the view
            cut it off), its height comes from the person's feet instead (their lowest 5 %). When
            it is not seen near the person at all, its tilt comes from the floor near the cameras.
        floor_near_distance: ... likewise when the refitted floor points lie, in the median,
            farther than this from the pelvis path along the floor (m): a camera framing the
            upper body sees the floor only metres away, where a few-% depth error is cm of height.
        seed: seed of RANSAC's sampling.
    """

    mask_dilation_px: int = 6
    mask_erosion_px: int = 1
    min_person_pixels: int = 30
    scale_frames: int = 60
    drift_seconds: float = 0.5
    mad_threshold: float = 3.0
    camera0_iterations: int = 6
    human_height: float = 1.70
    floor_frames: int = 30
    floor_pixel_stride: int = 4
    floor_depth_percentile: float = 95.0
    floor_radius: float = 3.0
    camera_floor_radius: float = 6.0
    voxel_size: float = 0.04
    normal_radius: float = 0.15
    up_tolerance_deg: float = 30.0
    camera_up_tolerance_deg: float = 45.0
    plane_threshold: float = 0.03
    floor_band: float = 0.1
    min_frame_floor_points: int = 30
    ransac_iterations: int = 300
    max_planes: int = 6
    floor_min_fraction: float = 0.3
    min_floor_points: int = 100
    floor_seen_fraction: float = 0.75
    floor_near_distance: float = 1.5
    seed: int = 0


@dataclass(frozen=True)
class Alignment:
    """How the input was brought into the world.

    Attributes:
        scale: metric = ``scale`` × input depth and camera translations.
        world_from_input: (4, 4) rigid map from the input's frame, after scaling, to the world.
        world_from_camera0: (4, 4) the first camera's pose in the world.
        floor_plane: (4,) the floor ``n·x + d = 0`` in the scaled input frame (``n`` up).
        up_source: ``"human+floor"`` or ``"camera+floor"``: which prior picked the floor.
        diagnostics: per-stage numbers (per-frame scales, inliers, plane list, feet height...).
    """

    scale: float
    world_from_input: np.ndarray
    world_from_camera0: np.ndarray
    floor_plane: np.ndarray
    up_source: str
    diagnostics: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """JSON-ready summary (for a clip's ``meta.json``)."""
        return {"scale": self.scale, "world_from_input": self.world_from_input.tolist(),
                "world_from_camera0": self.world_from_camera0.tolist(), "floor_plane": self.floor_plane.tolist(),
                "up_source": self.up_source, "diagnostics": self.diagnostics}


@dataclass(frozen=True)
class AlignResult:
    """What :func:`align` returns.

    Attributes:
        frames: metric, in the world, person removed (their mask kept).
        motion: the motion in the world (``None`` without one).
        alignment: the record.
    """

    frames: Frames
    motion: Motion | None
    alignment: Alignment


# --------------------------------------------------------------------------- helpers


def _grow(mask: np.ndarray, pixels: int) -> np.ndarray:
    """(T, H, W) masks dilated by a square of ``pixels`` (a separable max filter: fast on the stack)."""
    return maximum_filter(mask, size=(1, 2 * pixels + 1, 2 * pixels + 1)) if pixels > 0 else mask


def _shrink(mask: np.ndarray, pixels: int) -> np.ndarray:
    return minimum_filter(mask, size=(1, 2 * pixels + 1, 2 * pixels + 1)) if pixels > 0 else mask


def remove_person(frames: Frames, dilation_px: int = 6) -> Frames:
    """``frames`` with the depth under the dilated person mask made missing (the mask is kept)."""
    if frames.person_mask is None:
        return frames
    grown = _grow(frames.person_mask, dilation_px)
    return replace(frames, depth=np.where(grown, np.float32(0.0), frames.depth))


def transform_motion(motion: Motion, transforms: np.ndarray) -> Motion:
    """``motion`` moved rigidly by one (4, 4) transform or one per frame (T, 4, 4)."""
    m = np.asarray(transforms, dtype=np.float64)
    if m.shape == (4, 4):
        m = np.broadcast_to(m, (motion.num_frames, 4, 4))
    if m.shape != (motion.num_frames, 4, 4):
        raise ValueError(f"transforms must be (4, 4) or ({motion.num_frames}, 4, 4), got {m.shape}")
    root = Rotation.from_matrix(m[:, :3, :3]) * Rotation.from_quat(motion.root_quat, scalar_first=True)
    return replace(motion, root_pos=np.einsum("tij,tj->ti", m[:, :3, :3], motion.root_pos) + m[:, :3, 3],
                   root_quat=root.as_quat(scalar_first=True))


def _metric_poses(frames: Frames, scale: float) -> np.ndarray:
    poses = frames.cam_c2w.copy()
    poses[:, :3, 3] *= scale
    return poses


def _in_cameras(motion: MotionInput, frames: Frames, scale: float) -> Motion:
    """The motion with frame t in camera t's frame (metres)."""
    if motion.frame == "camera":
        return motion.motion
    poses = _metric_poses(frames, scale)
    return transform_motion(motion.motion, np.einsum("tij,jk->tik", np.linalg.inv(poses), poses[0]))


def _matched(motion: MotionInput, frames: Frames) -> MotionInput:
    """The motion at the video's frame rate, checked to cover the same frames."""
    if motion.frame == "world":
        raise ValueError(f"the motion {motion.source or ''} is in a world frame of its own (motion.npz / BVH) and "
                         "cannot be placed in the video; give camera-frame SMPL parameters (GVHMR-style) instead")
    m = motion.motion.resample(frames.fps)
    if m.num_frames != frames.num_frames:
        raise ValueError(f"the motion has {m.num_frames} frames at {frames.fps:g} fps but the video has "
                         f"{frames.num_frames}; they must cover the same frames")
    return replace(motion, motion=m)


# --------------------------------------------------------------------------- scale


def estimate_scale(frames: Frames, motion_camera: Motion, config: AlignConfig | None = None,
                   mesher: BodyMesher | None = None) -> tuple[float, dict]:
    """Metric scale of ``frames`` from the person: the humanoid of ``motion_camera`` (frame t in
    camera t's frame, metres) rendered into each camera against the depth at the person's pixels.

    Returns the scale and diagnostics. Raises ``ValueError`` when no person is visible.
    """
    cfg = config or AlignConfig()
    if frames.person_mask is None:
        raise ValueError("a motion was given but the video has no person masks; the scale is measured on the "
                         "person's pixels (give masks, person = 1)")
    mesher = mesher or BodyMesher(build_humanoid(HumanoidConfig(height=cfg.human_height)))
    measurable = _shrink(frames.person_mask, cfg.mask_erosion_px) & frames.valid
    counts = measurable.reshape(frames.num_frames, -1).sum(axis=1)
    eligible = np.flatnonzero(counts >= cfg.min_person_pixels)
    if len(eligible) == 0:
        raise ValueError(f"a motion was given but no person is visible: no frame has {cfg.min_person_pixels} "
                         f"person-mask pixels with depth (largest: {int(counts.max())}); check the masks")
    chosen = eligible[np.unique(np.linspace(0, len(eligible) - 1, min(cfg.scale_frames, len(eligible))).astype(int))]
    qpos = motion_camera.qpos()
    h, w = frames.image_size
    per_frame, used = [], []
    for t in chosen:
        body, _, _ = cast_mesh(mesher.pose(qpos[t]), mesher.faces, frames.intrinsic, np.eye(4), w, h)
        pixels = measurable[t] & (body > 0)
        if pixels.sum() >= cfg.min_person_pixels:
            per_frame.append(float(np.median(body[pixels] / frames.depth[t][pixels])))
            used.append(int(t))
    if not per_frame:
        raise ValueError("the motion's humanoid does not cover the person masks in any frame; is the motion in "
                         "this video's camera frame (GVHMR's smpl_params_incam)?")
    scales = np.array(per_frame)
    median = float(np.median(scales))
    mad = 1.4826 * float(np.median(np.abs(scales - median)))
    keep = np.abs(scales - median) <= cfg.mad_threshold * max(mad, 1e-3 * median)
    scale = float(np.median(scales[keep]))
    return scale, {"scale_per_frame": dict(zip(used, [round(s, 5) for s in per_frame])),
                   "scale_frames_used": int(keep.sum()), "scale_frames_rejected": int((~keep).sum()),
                   "scale_spread": float(mad / median)}


def depth_drift(per_frame: dict[int, float], scale: float, num_frames: int, fps: float,
                config: AlignConfig | None = None) -> np.ndarray:
    """(T,) per-frame depth factors: each frame's scale from the person (``per_frame``, frame →
    scale, as in :func:`estimate_scale`'s diagnostics) relative to the clip's ``scale``, with
    outliers dropped, interpolated over all frames and smoothed (``config.drift_seconds``)."""
    cfg = config or AlignConfig()
    if cfg.drift_seconds <= 0 or len(per_frame) < 2:
        return np.ones(num_frames)
    frames = np.array(sorted(per_frame))
    scales = np.array([per_frame[t] for t in frames])
    mad = 1.4826 * float(np.median(np.abs(scales - scale)))
    keep = np.abs(scales - scale) <= cfg.mad_threshold * max(mad, 1e-3 * scale)
    ratio = np.interp(np.arange(num_frames), frames[keep], scales[keep] / scale)
    return gaussian_filter1d(ratio, sigma=cfg.drift_seconds * fps, mode="nearest")


# --------------------------------------------------------------------------- floor and gravity


def human_up(motion_camera: Motion, frames: Frames, model=None) -> np.ndarray:
    """(3,) unit up direction of the person in the input frame: pelvis → head averaged over
    ``motion_camera`` (frame t in camera t's frame; ``model`` is the humanoid, default 1.70 m)."""
    body = compute_kinematics(motion_camera, model if model is not None else build_humanoid()).body_pos
    spine = body[:, BODY_NAMES.index("Head")] - body[:, BODY_NAMES.index("Pelvis")]
    spine /= np.linalg.norm(spine, axis=1, keepdims=True)
    up = np.einsum("tij,tj->i", frames.cam_c2w[:, :3, :3], spine)
    return up / np.linalg.norm(up)


def camera_up(frames: Frames) -> np.ndarray:
    """(3,) unit image-up direction of the cameras (minus their y axis) averaged over the video."""
    up = -frames.cam_c2w[:, :3, 1].sum(axis=0)
    return up / np.linalg.norm(up)


def _frame_points(frames: Frames, anchors: np.ndarray, radius: float, cfg: AlignConfig) -> list[np.ndarray]:
    """World points of evenly spread frames (every ``floor_pixel_stride``-th pixel) within
    ``radius`` of an anchor point, the farthest of each frame dropped."""
    chosen = np.unique(np.linspace(0, frames.num_frames - 1, min(cfg.floor_frames, frames.num_frames)).astype(int))
    s = cfg.floor_pixel_stride
    tree = cKDTree(anchors)
    points = []
    for t in chosen:
        depth = frames.depth[t, ::s, ::s]
        valid = depth > 0
        if valid.sum() < 3:
            continue
        valid &= depth <= np.percentile(depth[valid], cfg.floor_depth_percentile)
        pts = frames.world_points(t)[::s, ::s][valid]
        near = pts[tree.query(pts, distance_upper_bound=radius)[0] <= radius]
        if len(near):
            points.append(near)
    if not points:
        raise ValueError(f"no depth within {radius:g} m of the person (or the cameras) to find the floor in")
    return points


def _cloud(per_frame: list[np.ndarray], cfg: AlignConfig) -> tuple[np.ndarray, np.ndarray]:
    """All frames' points voxel-downsampled, and their unit normals."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(per_frame)))
    cloud = cloud.voxel_down_sample(cfg.voxel_size)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius, max_nn=30))
    return np.asarray(cloud.points), np.asarray(cloud.normals)








def _refine_per_frame(per_frame: list[np.ndarray], normal: np.ndarray, offset: float, up: np.ndarray,
                      cfg: AlignConfig) -> tuple[np.ndarray, float, list[np.ndarray]]:
    """The floor refitted frame by frame, then combined: the count-weighted mean normal, the
    median offset, and each refitted frame's floor points. A monocular depth map's scale errs
    per frame, which moves that frame's floor along the view (a few cm); a plane fitted to all
    frames at once would sit in whichever frames are densest, while the median over frames sits
    where most frames put it."""
    normals, weights, kept = [], [], []
    for pts in per_frame:
        near = pts[np.abs(pts @ normal + offset) < cfg.floor_band]
        if len(near) < cfg.min_frame_floor_points:
            continue
        n_t, d_t = fit_plane(near, up)
        for _ in range(2):  # the frame's own plane, without the band's other surfaces
            inliers = near[np.abs(near @ n_t + d_t) < cfg.plane_threshold]
            if len(inliers) < cfg.min_frame_floor_points:
                break
            n_t, d_t = fit_plane(inliers, up)
        else:
            normals.append(n_t)
            weights.append(len(inliers))
            kept.append(inliers)
    if not normals:
        return normal, offset, []
    normal = np.average(normals, axis=0, weights=weights)
    normal /= np.linalg.norm(normal)
    return normal, float(np.median([-np.median(p @ normal) for p in kept])), kept


def fit_floor(frames: Frames, up_prior: np.ndarray, tolerance_deg: float, anchors: np.ndarray, radius: float,
              config: AlignConfig | None = None) -> tuple[np.ndarray, float, dict]:
    """The floor of metric ``frames`` (person removed) within ``radius`` of the ``anchors``
    (N, 3) (the pelvis path, or the camera path): unit normal (up), offset ``d`` of
    ``n·x + d = 0``, and diagnostics. See the module docstring for the rule."""
    cfg = config or AlignConfig()
    rng = np.random.default_rng(cfg.seed)
    up_prior = np.asarray(up_prior, dtype=float) / np.linalg.norm(up_prior)
    min_cos = float(np.cos(np.radians(tolerance_deg)))
    per_frame = _frame_points(frames, np.asarray(anchors, dtype=float).reshape(-1, 3), radius, cfg)
    points, normals = _cloud(per_frame, cfg)
    remaining = points[np.abs(normals @ up_prior) >= min_cos]
    planes = []
    for _ in range(cfg.max_planes):
        found = ransac_plane(remaining, up_prior, min_cos, cfg.plane_threshold, cfg.ransac_iterations, rng)
        if found is None or found[2].sum() < cfg.min_floor_points:
            break
        normal, offset, inliers = found
        planes.append({"normal": normal, "offset": offset, "points": int(inliers.sum()),
                       "height": float(np.median(remaining[inliers] @ up_prior))})
        remaining = remaining[~inliers]
    if not planes:
        raise ValueError(f"found no floor: no plane of {cfg.min_floor_points}+ points within {tolerance_deg:g} deg "
                         f"of the up direction {np.round(up_prior, 3).tolist()}")
    largest = max(p["points"] for p in planes)
    floor = min((p for p in planes if p["points"] >= cfg.floor_min_fraction * largest), key=lambda p: p["height"])
    normal, offset, kept = _refine_per_frame(per_frame, floor["normal"], floor["offset"], up_prior, cfg)
    searched = min(cfg.floor_frames, frames.num_frames)
    # how far from the anchors the floor was seen, along the floor: a floor seen only metres
    # away sets its height less reliably than the feet do
    along = plane_axes(normal).T
    tree = cKDTree(np.asarray(anchors, dtype=float).reshape(-1, 3) @ along)
    distance = float(np.median(tree.query(np.concatenate(kept) @ along)[0])) if kept else float("inf")
    diagnostics = {
        "floor_frames": len(kept), "floor_distance_m": distance, "floor_frames_searched": searched,
        "floor_points": floor["points"], "cloud_points": len(points),
        "up_prior_to_floor_deg": float(np.degrees(np.arccos(np.clip(normal @ up_prior, -1, 1)))),
        "planes": [{"height": round(p["height"], 4), "points": p["points"],
                    "tilt_deg": round(float(np.degrees(np.arccos(np.clip(p["normal"] @ up_prior, -1, 1)))), 2)}
                   for p in planes]}
    return normal, offset, diagnostics


# --------------------------------------------------------------------------- align


def _world_frame(normal: np.ndarray, offset: float, origin: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """(4, 4) rigid map to a world with z = ``normal``, the origin at ``origin`` dropped onto the
    plane, x along ``forward`` projected onto it."""
    origin = origin - (normal @ origin + offset) * normal
    x = forward - (forward @ normal) * normal
    if np.linalg.norm(x) < 1e-6:  # looking straight down: any horizontal direction will do
        x = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(normal, x), normal])
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = -rot @ origin
    return out


def align(frames: Frames, motion: MotionInput | None = None, config: AlignConfig | None = None,
          metric: bool = False) -> AlignResult:
    """Bring ``frames`` (and ``motion``) into a metric, gravity-aligned world with the floor at z = 0.

    With a camera-frame ``motion`` (see :class:`crisp_gym.reconstruct.io.MotionInput`) the scale comes from
    the person (unless ``metric``: the depth is trusted as metres) and the person's up direction
    picks the floor. Without one, ``metric=True`` is required and the cameras' image-up picks it.
    """
    cfg = config or AlignConfig()
    diagnostics: dict = {}
    if motion is None and not metric:
        raise ValueError("without a motion the scale is unknown: pass a camera-frame motion, or metric=True "
                         "(--metric) if the depth is in metres")
    removed = remove_person(frames, cfg.mask_dilation_px)
    motion_cam = None
    if motion is not None:
        motion = _matched(motion, frames)
        mesher = BodyMesher(build_humanoid(HumanoidConfig(height=cfg.human_height)))
        if metric:
            scale = 1.0
        elif motion.frame == "camera":
            scale, found = estimate_scale(frames, motion.motion, cfg, mesher)
            diagnostics.update(found)
        else:
            # Placing a first-camera motion in camera t needs the scale (of the camera baselines):
            # start with the cameras' rotations alone (scale 0), then iterate to the fixed point.
            scale = 0.0
            for _ in range(cfg.camera0_iterations):
                previous = scale
                scale, found = estimate_scale(frames, _in_cameras(motion, frames, scale), cfg, mesher)
                if abs(scale - previous) < 1e-4 * scale:
                    break
            diagnostics.update(found)
        motion_cam = _in_cameras(motion, frames, scale)
        up_prior = human_up(motion_cam, frames, mesher.model)
        tolerance, source = cfg.up_tolerance_deg, "human+floor"
    else:
        scale = 1.0
        up_prior, tolerance, source = camera_up(frames), cfg.camera_up_tolerance_deg, "camera+floor"
    metric_frames = removed.scaled(scale)
    if "scale_per_frame" in diagnostics:
        drift = depth_drift(diagnostics["scale_per_frame"], scale, frames.num_frames, frames.fps, cfg)
        metric_frames = replace(metric_frames, depth=metric_frames.depth * drift[:, None, None].astype(np.float32))
        diagnostics["depth_drift_range"] = [float(drift.min()), float(drift.max())]
    poses = metric_frames.cam_c2w
    cameras = poses[:, :3, 3]
    if motion_cam is None:
        normal, offset, found = fit_floor(metric_frames, up_prior, tolerance, cameras, cfg.camera_floor_radius, cfg)
    else:
        pelvis = np.einsum("tij,tj->ti", poses[:, :3, :3], motion_cam.root_pos) + cameras
        try:
            normal, offset, found = fit_floor(metric_frames, up_prior, tolerance, pelvis, cfg.floor_radius, cfg)
        except ValueError:  # no floor in view near the person: its tilt from farther away, its height from the feet
            normal, offset, found = fit_floor(metric_frames, up_prior, tolerance, np.concatenate([pelvis, cameras]),
                                              cfg.camera_floor_radius, cfg)
            found |= {"floor_frames": 0, "floor_search": "near the cameras"}
    diagnostics.update(found)
    diagnostics["up_prior"] = up_prior.tolist()
    origin = cameras[0] if motion_cam is None else pelvis[0]
    world_from_input = _world_frame(normal, offset, origin, poses[0, :3, 2])
    world_motion = None
    diagnostics["floor_height_source"] = "scene"
    if motion_cam is not None:
        world_motion = transform_motion(motion_cam, np.einsum("ij,tjk->tik", world_from_input, poses))
        feet = float(np.percentile(foot_sole_heights(world_motion, mesher.model), 5))
        rarely_seen = diagnostics["floor_frames"] < cfg.floor_seen_fraction * diagnostics["floor_frames_searched"]
        if rarely_seen or diagnostics["floor_distance_m"] > cfg.floor_near_distance:
            # The floor under the person was rarely in view, or only metres away (far depth is
            # the noisiest): the feet, which touch it, set its height; its tilt still comes
            # from the scene.
            world_from_input[2, 3] -= feet
            offset -= feet
            world_motion = world_motion.translated([0.0, 0.0, -feet])
            diagnostics["floor_height_source"] = "feet"
            diagnostics["floor_moved_to_feet_m"] = feet
            feet = 0.0
        diagnostics["feet_height_m"] = feet
    alignment = Alignment(scale=scale, world_from_input=world_from_input,
                          world_from_camera0=world_from_input @ poses[0], floor_plane=np.r_[normal, offset],
                          up_source=source, diagnostics=diagnostics)
    return AlignResult(frames=metric_frames.transformed(world_from_input), motion=world_motion, alignment=alignment)
