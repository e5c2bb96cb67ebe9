"""A plain video (mp4/mov or a folder of images) → a simulation-ready clip, offline on a CPU.

The fast path next to the high-fidelity one (MegaSAM depth + GVHMR motion through
:mod:`crisp_gym.reconstruct.pipeline`): no depth network, no learned human mesh, no GPU, nothing downloaded.

1. **person** (:mod:`crisp_gym.reconstruct.person`): MediaPipe Pose, 33 landmarks in pixels and in metres
   (centred between the hips) and a mask, per frame;
2. **cameras** (:mod:`crisp_gym.reconstruct.sfm`): COLMAP on the frames with the person masked out, up to
   scale; a fixed camera when too few frames register (or ``use_sfm=False``, a tripod);
3. **person in the camera** (:func:`person_in_camera`): the landmarks' metric 3D shape placed by
   PnP against their pixels;
4. **scale** (:func:`metric_scale`): the person's depth at the lowest foot against the depth where
   that foot's ray meets the plane of the scene points around it (median ratio over the frames:
   the person is metric, SfM is not). The person's size is MediaPipe's, or a stature the user
   gives (:mod:`reconstruct.body_scale`); once the floor is found, a second measure of the scale,
   by heights above it where this one measures depths, is recorded (and warned about when the two
   disagree);
5. **floor and gravity** (:func:`floor_frame`): the plane of scene points under the feet, its
   normal within :attr:`VideoConfig.max_floor_tilt_deg` of the person's trunk; without scene points
   (or when the feet do not stand on that plane), the plane through the feet's lowest landmarks;
6. **motion** (:mod:`crisp_gym.reconstruct.landmarks`, :func:`settle`): the landmarks, given our bone lengths,
   retargeted onto the humanoid; under each seat contact the seat the scene points show is found
   (:func:`find_seats`), and the hips are lowered onto it and each planted foot put on the floor, the
   knees re-solved (a monocular estimate of a seated person floats about 20 cm above the seat, and
   its planted feet hover by centimetres);
7. **scene** (:mod:`crisp_gym.reconstruct.sparse_planes`): the ground, level tops the points show plainly,
   the seats; then the supports the contacts need and the scene lacks (:mod:`crisp_gym.reconstruct.contact`).

``meta.json`` records quality flags (:func:`quality_flags`) and warns when they are poor.
"""

from __future__ import annotations

import importlib.util
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from crisp_gym.geometry import fit_plane, ransac_plane
from crisp_gym.humanoid import BODY_NAMES, build_humanoid
from crisp_gym.metrics import foot_heights, sole_points
from crisp_gym.motion import Motion, compute_kinematics, planted_feet
from crisp_gym.reconstruct.body_scale import ground_metrology, implied_stature, stature_factor
from crisp_gym.reconstruct.contact import (
    PARTS,
    CompletionResult,
    ContactConfig,
    body_geometry,
    contact_completion,
    filter_contacts,
    kinematic_contacts,
)
from crisp_gym.reconstruct.landmarks import (
    fill_gaps,
    hips_and_trunk,
    landmarks_to_motion,
    leg_lengths,
    with_leg_lengths,
)
from crisp_gym.reconstruct.person import MEDIAPIPE_VERSION, PersonTrack, landmark, runtime_installed, track_person
from crisp_gym.reconstruct.sfm import CameraSolve, SfmConfig, prior_intrinsic, solve_cameras, static_camera
from crisp_gym.reconstruct.sparse_planes import SparsePlaneConfig, ground_box, level_tops, seat_surface
from crisp_gym.reconstruct.video_cache import cached_cameras, cached_track, frames_digest
from crisp_gym.scene import Box

FEET = ("left_heel", "right_heel", "left_foot_index", "right_foot_index", "left_ankle", "right_ankle")
"""Landmarks the lowest point of a foot is taken from."""
_FEET_INDEX = [landmark(n) for n in FEET]
_LOWERED_KEEP = FEET + ("left_knee", "right_knee")  # landmarks not moved when the hips are lowered


@dataclass(frozen=True)
class VideoConfig:
    """Every setting of the video path.

    Attributes:
        fps: output motion rate (the video's frames are resampled to it).
        sfm: structure-from-motion settings.
        use_sfm: ``False`` skips structure from motion: a fixed camera (a tripod), the scene from
            the person alone.
        scale_window_px: scene points within this many pixels of the lowest foot give its depth.
        min_visibility: landmarks below this visibility are left out of PnP.
        max_floor_tilt_deg: the floor's normal within this angle of the person's trunk.
        floor_threshold: m, inlier distance of the floor plane.
        ransac_iterations: plane hypotheses the floor's RANSAC draws.
        floor_feet_tolerance: m; the scene points' plane is the floor only if the feet's lowest
            landmarks stand within this of it (else a kerb or a bank was found, and the feet's
            own plane is the floor); the person's placement by PnP wanders by ±10 cm.
        planes: the horizontal surfaces.
        contact: contact detection and completion.
        seat_drop_max: m; a seat contact this far at most above a surface the scene saw is
            lowered onto it (farther: the surface is another one, and a support is completed).
        seat_blend: s; the hips are lowered and raised over this time at the ends of a seat contact.
        upright_hip_share: frames whose hips are at least this share of their highest are standing
            or walking, and their median trunk is made vertical (:func:`upright`).
        person_height: m, the person's stature when known: the scene is scaled so that their legs
            have this stature's length (:func:`~reconstruct.body_scale.stature_factor`); ``None``
            takes MediaPipe's body size as it is (recorded as ``implied_stature_m``).
        scale_check_tolerance: a second measure of the scale, by metrology against the floor
            (:func:`~reconstruct.body_scale.ground_metrology`), off by more than this share is warned about.
        trunk_to_floor_warning_deg: a floor whose normal is more than this off the person's median
            trunk is warned about (:func:`floor_warning`).
    """

    fps: float = 30.0
    sfm: SfmConfig = field(default_factory=SfmConfig)
    use_sfm: bool = True
    scale_window_px: float = 40.0
    min_visibility: float = 0.5
    max_floor_tilt_deg: float = 20.0
    floor_threshold: float = 0.03
    ransac_iterations: int = 500
    floor_feet_tolerance: float = 0.12
    planes: SparsePlaneConfig = field(default_factory=SparsePlaneConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)
    seat_drop_max: float = 0.35
    seat_blend: float = 0.3
    upright_hip_share: float = 0.85
    person_height: float | None = None
    scale_check_tolerance: float = 0.15
    trunk_to_floor_warning_deg: float = 12.0

    def __post_init__(self) -> None:
        if self.person_height is not None and not 0.5 <= self.person_height <= 2.5:
            raise ValueError(f"person_height must be a human stature in metres (0.5-2.5), got {self.person_height}")
        if not 0.0 < self.scale_check_tolerance < 1.0:
            raise ValueError(f"scale_check_tolerance must be in (0, 1), got {self.scale_check_tolerance}")


@dataclass(frozen=True)
class VideoReconstruction:
    """What :func:`reconstruct_video` returns.

    Attributes:
        boxes: planar then contact primitives, floor frame.
        motion: the humanoid motion in the floor frame at ``config.fps``.
        person: the MediaPipe track (video frames).
        cameras: the camera solve (SfM units, or a fixed camera).
        scale: metres per SfM unit (1 for a fixed camera).
        world_from_sfm: (4, 4) from the metric SfM frame to the floor frame.
        landmarks: (T, 33, 3) metric landmarks in the floor frame (video frames).
        completion: the contact completion.
        flags: quality figures (see :func:`quality_flags`).
        timings: seconds per stage.
    """

    boxes: list[Box]
    motion: Motion
    person: PersonTrack
    cameras: CameraSolve
    scale: float
    world_from_sfm: np.ndarray
    landmarks: np.ndarray
    completion: CompletionResult | None
    flags: dict
    timings: dict[str, float]

    def camera_in_world(self) -> np.ndarray:
        """(T, 4, 4) camera-to-floor-frame poses (OpenCV camera), metric."""
        c2w = self.cameras.cam_c2w.copy()
        c2w[:, :3, 3] *= self.scale
        return self.world_from_sfm @ c2w


def person_in_camera(track: PersonTrack, intrinsic: np.ndarray, min_visibility: float = 0.5) -> np.ndarray:
    """(T, 33, 3) landmarks in the camera frame (metres): their metric shape placed by PnP."""
    out = np.full(track.world.shape, np.nan)
    for k in np.flatnonzero(track.found):
        use = track.visibility[k] >= min_visibility
        if use.sum() < 6:
            use = np.argsort(track.visibility[k])[-6:]
        obj, img = track.world[k][use].astype(np.float64), track.image[k][use].astype(np.float64)
        ok, rvec, tvec = cv2.solvePnP(obj, img, intrinsic, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, intrinsic, None, rvec, tvec)
        if tvec[2, 0] <= 0:
            continue
        out[k] = track.world[k] @ cv2.Rodrigues(rvec)[0].T + tvec.ravel()
    return out


def _lowest_foot(track: PersonTrack, k: int) -> int:
    return _FEET_INDEX[int(np.argmax(track.image[k, _FEET_INDEX, 1]))]


def metric_scale(track: PersonTrack, in_camera: np.ndarray, cameras: CameraSolve,
                 window_px: float) -> tuple[float, np.ndarray]:
    """Metres per SfM unit and the per-keyframe ratios it is the median of (see module docstring)."""
    ratios = []
    for i, k in enumerate(cameras.keyframes):
        if not cameras.registered[i] or not np.isfinite(in_camera[k, 0, 0]) or len(cameras.visible[i]) == 0:
            continue
        foot = _lowest_foot(track, k)
        w2c = np.linalg.inv(cameras.cam_c2w[k])
        points = cameras.points[cameras.visible[i]] @ w2c[:3, :3].T + w2c[:3, 3]
        pixels = points @ cameras.intrinsic.T
        pixels = pixels[:, :2] / pixels[:, 2:3]
        near = np.linalg.norm(pixels - track.image[k, foot], axis=1) < window_px
        if near.sum() < 5:
            continue
        # The foot's ray met with the plane of the points around it: their median depth would be
        # biased far, as a slanted floor's image rows crowd together with distance.
        ray = np.linalg.solve(cameras.intrinsic, [*track.image[k, foot], 1.0])
        normal, offset = fit_plane(points[near], -ray)
        if abs(normal @ ray) > 1e-3 * np.linalg.norm(ray):
            depth = -offset / (normal @ ray)  # z of the ray's point (ray has z = 1)
            if depth > 0:
                ratios.append(in_camera[k, foot, 2] / depth)
    ratios = np.asarray(ratios)
    if len(ratios) < 3:
        raise ValueError("too few frames show scene points next to the person's feet to measure the scale")
    return float(np.median(ratios)), ratios


def floor_frame(landmarks: np.ndarray, points: np.ndarray, view: np.ndarray, cfg: VideoConfig,
                rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """(4, 4) transform from the metric SfM (or camera) frame to the floor frame, and its figures.

    Up is the floor plane's normal (signed along the person's trunk); the floor is z = 0; x is
    the first camera's viewing direction ``view`` laid level; the origin is under the person's
    first position.
    """
    hips, trunk = hips_and_trunk(landmarks)
    ok = np.isfinite(trunk).all(axis=1)
    up = np.median(trunk[ok] / np.linalg.norm(trunk[ok], axis=1, keepdims=True), axis=0)
    up /= np.linalg.norm(up)
    feet = landmarks[ok][:, _FEET_INDEX]  # (K, 6, 3)
    lowest = feet[np.arange(len(feet)), np.argmin(feet @ up, axis=1)]
    min_cos = np.cos(np.deg2rad(cfg.max_floor_tilt_deg))
    source, found = "feet", None
    if len(points):
        offsets = points[:, None, :] - lowest[None, ::5, :]
        horizontal = offsets - (offsets @ up)[..., None] * up
        near = points[np.linalg.norm(horizontal, axis=2).min(axis=1) < 1.0]
        if len(near) >= 30:
            found = ransac_plane(near, up, min_cos, cfg.floor_threshold, cfg.ransac_iterations, rng)
        if found is not None:
            # The floor is the level layer the feet stand on, not one above or below them (a kerb, a step).
            stand = np.percentile(lowest @ found[0] + found[1], 10)
            source = "scene points" if abs(stand) <= cfg.floor_feet_tolerance else "feet"
    if source == "feet":
        found = ransac_plane(lowest, up, min_cos, cfg.floor_threshold, cfg.ransac_iterations, rng)
    # Feet too scattered for any plane: level with the trunk through their median height.
    normal, offset, inliers = found or (up, -float(np.median(lowest @ up)), np.zeros(len(lowest), bool))
    x = view - (view @ normal) * normal
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(normal, x), normal])  # rows: the floor frame's axes
    first = hips[np.flatnonzero(ok)[0]]
    origin = first - (first @ normal + offset) * normal
    transform = np.eye(4)
    transform[:3, :3] = rot
    transform[:3, 3] = -rot @ origin
    tilt = float(np.degrees(np.arccos(np.clip(normal @ up, -1.0, 1.0))))
    return transform, {"floor_source": source, "floor_inliers": int(inliers.sum()), "trunk_to_floor_deg": tilt}



def floor_warning(floor: dict, cameras: CameraSolve, max_tilt_deg: float) -> str | None:
    """A warning when the floor (``floor_frame``'s figures) leans more than ``max_tilt_deg`` against
    the person's median trunk. MediaPipe's trunk leans a few degrees (2.6-9.1° on the bundled real
    video's full camera solves); 12-20° came with solves COLMAP cut short under load (30-48 of 64
    frames), whose camera stood 0.6-1.0 m or 2.1 m above the floor (1.6-1.9 m on the others)."""
    tilt = floor["trunk_to_floor_deg"]
    if tilt <= max_tilt_deg:
        return None
    solve = "a fixed camera" if cameras.static else (
        f"the camera solve, {int(cameras.registered.sum())} of {len(cameras.keyframes)} frames registered")
    return (f"the floor ({floor['floor_source']}) leans {tilt:.0f}° against the person's trunk: the floor or "
            f"{solve} is doubtful, and heights above the floor with it")


def upright(landmarks: np.ndarray, hip_share: float) -> tuple[np.ndarray, float]:
    """Landmarks turned, each frame about its hips' midpoint, by the one rotation that makes the
    person's median trunk vertical over the frames they stand or walk in (hips above ``hip_share`` of
    their highest), and that rotation's angle in degrees.

    MediaPipe's 3D pose leans towards the image's vertical: with the camera pitched 15° down on the
    bundled real video, the walking trunk came out 6-12° off the floor's normal, mostly towards the
    camera, and the humanoid leaned back 13-24° in its walk. People stand and walk upright on
    average; a seated or bending trunk keeps its lean relative to that."""
    hips, trunk = hips_and_trunk(landmarks)
    ok = np.isfinite(trunk).all(axis=1)
    height = np.where(ok, hips[:, 2], -np.inf)
    standing = ok & (height >= hip_share * height.max())
    if standing.sum() < 3:
        return landmarks, 0.0
    mean = np.median(trunk[standing] / np.linalg.norm(trunk[standing], axis=1, keepdims=True), axis=0)
    mean /= np.linalg.norm(mean)
    axis = np.cross(mean, [0.0, 0.0, 1.0])
    angle = float(np.arctan2(np.linalg.norm(axis), mean[2]))
    if angle < 1e-9:
        return landmarks, 0.0
    turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    return (landmarks - hips[:, None]) @ turn.T + hips[:, None], float(np.degrees(angle))


def _two_bone_knee(hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray, thigh: float, shin: float) -> np.ndarray:
    """Knee positions (T, 3) reaching ``ankle`` from ``hip`` with the given bone lengths, bent
    forward and up (a seated knee rises above a lowered hip; its sideways splay in a monocular
    estimate is the least certain part and would push the hip past its range)."""
    reach = ankle - hip
    dist = np.clip(np.linalg.norm(reach, axis=1), abs(thigh - shin) + 1e-6, thigh + shin - 1e-6)
    axis = reach / np.linalg.norm(reach, axis=1, keepdims=True)
    along = (thigh**2 - shin**2 + dist**2) / (2 * dist)
    height = np.sqrt(np.maximum(thigh**2 - along**2, 0.0))
    forward = knee - ankle  # the shin's lean: the knee is ahead of and above the ankle
    forward[:, 2] = np.maximum(forward[:, 2], 0.0) + 1.0
    side = forward - np.sum(forward * axis, axis=1, keepdims=True) * axis
    side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-9)
    return hip + along[:, None] * axis + height[:, None] * side


@dataclass(frozen=True)
class Seat:
    """A seat the scene points show under a seat contact: its box and the contact's frames ``[start, stop)``."""

    box: Box
    start: int
    stop: int
    bodies: tuple[str, ...]

    @property
    def top(self) -> float:
        return float(self.box.center[2] + self.box.half_size[2])


def find_seats(motion: Motion, points: np.ndarray, cfg: VideoConfig) -> list[Seat]:
    """The seats under the motion's seat contacts (:func:`~crisp_gym.reconstruct.sparse_planes.seat_surface`)."""
    geometry = body_geometry(motion)
    contacts = filter_contacts(kinematic_contacts(motion, cfg.contact.kinematic, geometry), motion,
                               cfg.contact.filter, geometry)
    found = []
    for group in _overlapping([c for c in contacts if c.body in PARTS["seat"]]):
        box = seat_surface(points, np.concatenate([c.points for c in group]), cfg.seat_drop_max, cfg.planes)
        if box is not None:
            found.append(Seat(replace(box, name=f"seat_{len(found)}"), min(c.start for c in group),
                              max(c.stop for c in group), tuple(sorted({c.body for c in group}))))
    return found


def seated_underside(motion: Motion) -> np.ndarray:
    """(T,) height of the body's underside where it sits: the 10 % quantile of the seat parts' contact patches."""
    geometry = body_geometry(motion)
    patches = [geometry.patches[BODY_NAMES.index(b)][..., 2] for b in PARTS["seat"]]
    return np.quantile(np.concatenate(patches, axis=1), 0.1, axis=1)


def seat_gaps(motion: Motion, seats: list[Seat]) -> np.ndarray:
    """Per seat, the median height of the seated body's underside above the seat's top over its frames."""
    underside = seated_underside(motion)
    return np.array([np.median(underside[s.start:s.stop]) - s.top for s in seats])


def hip_drop(seats: list[Seat], depths: np.ndarray, num_frames: int, ramp: int) -> np.ndarray:
    """(T,) metres the hips are lowered: each seat's depth over its frames, eased in and out over ``ramp`` frames."""
    frames = np.arange(num_frames)
    drop = np.zeros(num_frames)
    for seat, depth in zip(seats, depths):
        weight = np.clip(1.0 - np.maximum(seat.start - frames, frames - (seat.stop - 1)) / (ramp + 1), 0.0, 1.0)
        drop = np.maximum(drop, depth * weight)
    return drop


def settle(landmarks: np.ndarray, first: Motion, seats: list[Seat], cfg: VideoConfig, model,
           iterations: int = 8) -> tuple[Motion, np.ndarray]:
    """The motion with each planted foot on the floor and the hips resting on ``seats``, and each
    seat's final gap (m).

    The retarget's stance grounding moves the whole body to put the lower planted foot on the
    floor; a monocular estimate lets the other foot hover by centimetres and a seated body float
    a hand's width above its seat. Here, in the landmarks (whose legs already have our lengths and
    which stand where ``first`` does), each foot planted in ``first`` is moved to the floor and the
    hips onto their seat (and any other foot below the floor up to it), the knees are re-solved,
    and the motion is retargeted without moving the body up or down. The knees' new bend moves
    the feet again, so both moves are refined from what remains: the foot's by half of it (the
    full step overshoots and oscillates; measured on the bundled real video: planted feet median
    0.0 cm, p90 2.2 cm after 8 steps)."""
    thigh, shin = leg_lengths(model)
    ramp = max(1, int(round(cfg.seat_blend * first.fps)))
    depths = np.maximum(seat_gaps(first, seats), 0.0) if seats else np.zeros(0)
    planted = planted_feet(first, model)
    lift = np.zeros((first.num_frames, 2))
    motion = first
    for _ in range(iterations):
        heights = foot_heights(sole_points(model, motion.qpos()))
        # Planted feet onto the floor; any other foot at least out of it (a swinging foot 4 cm under
        # the floor is pushed up by the simulated contact and trips the body).
        error = np.where(planted, heights, np.minimum(heights, 0.0))
        lift -= 0.5 * gaussian_filter1d(error, cfg.seat_blend * first.fps / 3, axis=0)
        adjusted = adjust_legs(landmarks, hip_drop(seats, depths, first.num_frames, ramp), lift, thigh, shin)
        motion = landmarks_to_motion(adjusted, first.fps, model=model, shift=False).motion
        if seats:
            depths = np.maximum(depths + seat_gaps(motion, seats), 0.0)
    return motion, seat_gaps(motion, seats) if seats else np.zeros(0)


def _passed_through(box: Box, body_pos: np.ndarray, soles: np.ndarray, margin: float = 0.02) -> bool:
    """Whether the person went through ``box``: a joint or sole point inside it, or, in some frame,
    a sole inside its footprint and under its top while both knees are above it (the shins cross
    a slab a few centimetres thick, which no point lands in). ``body_pos`` (T, 24, 3) are the
    joints, ``soles`` (T, 4, 3) the sole corners. A level top the person walked through is a slice
    of a slope or a bush, not a surface."""
    points = np.concatenate([body_pos, soles], axis=1)
    local = (points - box.center) @ box.rotation
    if np.any(np.all(np.abs(local) <= box.half_size - margin, axis=-1)):
        return True
    top = box.top_height()
    sole_local = local[:, body_pos.shape[1]:]
    under = np.all(np.abs(sole_local[..., :2]) <= box.half_size[:2] - margin, axis=-1) & (soles[..., 2] < top - margin)
    knees = body_pos[:, [BODY_NAMES.index("L_Knee"), BODY_NAMES.index("R_Knee")], 2].min(axis=1)
    return bool(np.any(under.any(axis=1) & (knees > top + margin)))


def _overlapping(contacts: list) -> list[list]:
    """Contacts grouped by overlapping frame windows (the pelvis and both thighs on one seat)."""
    groups: list[list] = []
    for contact in sorted(contacts, key=lambda c: c.start):
        if groups and contact.start < max(c.stop for c in groups[-1]):
            groups[-1].append(contact)
        else:
            groups.append([contact])
    return groups


def adjust_legs(points: np.ndarray, hip_drop: np.ndarray, foot_lift: np.ndarray, thigh: float,
                shin: float) -> np.ndarray:
    """Landmarks with everything above the knees lowered by ``hip_drop`` (T,), each foot raised
    by ``foot_lift`` (T, 2: left, right), and the knees re-solved for legs of the given lengths."""
    out = points.copy()
    moved = [i for i in range(points.shape[1]) if i not in {landmark(n) for n in _LOWERED_KEEP}]
    out[:, moved, 2] -= hip_drop[:, None]
    for k, side in enumerate(("left", "right")):
        hip, knee, ankle = (landmark(f"{side}_{j}") for j in ("hip", "knee", "ankle"))
        foot = [ankle, landmark(f"{side}_heel"), landmark(f"{side}_foot_index")]
        out[:, foot, 2] += foot_lift[:, k, None]
        out[:, knee] = _two_bone_knee(out[:, hip], points[:, knee], out[:, ankle], thigh, shin)
    return out


def resample_landmarks(points: np.ndarray, fps_in: float, fps_out: float) -> np.ndarray:
    """Landmarks at ``fps_out`` (linear in time; positions, so no wrapping)."""
    t_in = np.arange(len(points)) / fps_in
    t_out = np.arange(0.0, t_in[-1] + 1e-9, 1.0 / fps_out)
    flat = points.reshape(len(points), -1)
    return np.stack([np.interp(t_out, t_in, flat[:, k]) for k in range(flat.shape[1])], axis=1).reshape(
        len(t_out), *points.shape[1:])


def quality_flags(track: PersonTrack, cameras: CameraSolve, scale: float, scale_ratios: np.ndarray,
                  in_camera: np.ndarray) -> tuple[dict, list[str]]:
    """The figures ``meta.json`` records about the input, and warnings where they are poor.

    ``parallax`` is the camera's largest displacement over the person's median distance from it."""
    depth = np.nanmedian(in_camera[..., 2]) if np.isfinite(in_camera).any() else float("nan")
    flags = {
        "frames": int(len(track.found)),
        "person_found": round(float(track.found.mean()), 3),
        "leg_visibility": round(float(np.mean(track.visibility[track.found][:, _FEET_INDEX])), 3)
        if track.found.any() else 0.0,
        "static_camera": cameras.static,
        "static_reason": cameras.reason,
        "keyframes": int(len(cameras.keyframes)),
        "registered": int(cameras.registered.sum()),
        "reprojection_error_px": None if cameras.static else round(cameras.reprojection_error, 3),
        "scene_points": int(len(cameras.points)),
        "camera_rotation_deg": round(cameras.rotation_deg(), 2),
        "parallax": None if cameras.static else round(scale * cameras.baseline() / max(depth, 1e-6), 4),
        "scale_samples": int(len(scale_ratios)),
        "scale_spread": None if len(scale_ratios) < 3 else round(
            float(np.subtract(*np.percentile(scale_ratios, [75, 25])) / np.median(scale_ratios)), 4),
    }
    warn = []
    if flags["person_found"] < 0.8:
        warn.append(f"the person is found in only {100 * flags['person_found']:.0f} % of the frames")
    if flags["leg_visibility"] < 0.6:
        warn.append(f"the feet are poorly visible (mean visibility {flags['leg_visibility']:.2f}): "
                    f"contacts and the floor are guessed")
    if cameras.static:
        warn.append(f"fixed camera ({cameras.reason}): the scene comes from the person alone (floor from the feet, "
                    f"seats from where the hips rest)")
    elif flags["scale_spread"] is not None and flags["scale_spread"] > 0.15:
        warn.append(f"the metric scale is uncertain (interquartile spread {100 * flags['scale_spread']:.0f} %)")
    return flags, warn


def check_video_extras(use_sfm: bool = True) -> None:
    """ModuleNotFoundError naming the install step when the video path's optional parts are missing."""
    missing = []
    if use_sfm and importlib.util.find_spec("pycolmap") is None:
        missing.append("pycolmap (pip install 'crisp-gym[video]')")
    if not runtime_installed():
        missing.append(f"MediaPipe {MEDIAPIPE_VERSION} in its own folder (python -m crisp_gym.reconstruct.person --install)")
    if missing:
        raise ModuleNotFoundError("the video path needs " + " and ".join(missing) + "; scripts/install.sh does both")


def reconstruct_video(frames: np.ndarray, fps: float, config: VideoConfig | None = None, seed: int = 0,
                      progress: bool = True, cache: Path | None = None) -> VideoReconstruction:
    """Run the stages of the module docstring on ``frames`` ((T, H, W, 3) uint8 RGB at ``fps``);
    the person track and the camera solve are kept in and reused from the folder ``cache``
    (:mod:`reconstruct.video_cache`) when it is given."""
    cfg = config or VideoConfig()
    check_video_extras(cfg.use_sfm)
    rng = np.random.default_rng(seed)
    timings: dict[str, float] = {}
    digest = frames_digest(frames) if cache is not None else ""
    start = time.perf_counter()
    track, track_cached = cached_track(cache, digest, lambda: track_person(frames, progress=progress))
    timings["person"] = time.perf_counter() - start
    if track.found.sum() < 2:
        raise ValueError(f"no person found in the video ({track.found.sum()} of {len(frames)} frames)")

    start = time.perf_counter()
    height, width = frames.shape[1:3]
    if cfg.use_sfm:
        cameras, cameras_cached = cached_cameras(cache, digest, repr(cfg.sfm),
                                                 lambda: solve_cameras(frames, track.masks, cfg.sfm, progress=progress))
    else:
        cameras_cached = False
        cameras = static_camera(len(frames), prior_intrinsic(height, width, cfg.sfm.focal_factor),
                                "a fixed camera was asked for (--fixed-camera)")
    timings["cameras"] = time.perf_counter() - start

    start = time.perf_counter()
    in_camera = person_in_camera(track, cameras.intrinsic, cfg.min_visibility)
    try:
        stature = round(implied_stature(track, cfg.min_visibility), 3)
    except ValueError:  # legs too rarely seen: only a given stature needs them
        stature = None
    body = {"implied_stature_m": stature, "person_height_m": cfg.person_height}
    if cfg.person_height is not None:
        # A larger person seen in the same pixels stands proportionally farther: the landmarks
        # scale about the camera's centre, and the scene with them.
        in_camera = in_camera * stature_factor(track, cfg.person_height, cfg.min_visibility)
    scale, ratios = 1.0, np.zeros(0)
    if not cameras.static:
        try:
            scale, ratios = metric_scale(track, in_camera, cameras, cfg.scale_window_px)
        except ValueError as err:  # the scene is there but cannot be scaled: treat the camera as fixed
            cameras = static_camera(len(frames), cameras.intrinsic, str(err), cameras.seconds)
    c2w = cameras.cam_c2w.copy()
    c2w[:, :3, 3] *= scale
    in_sfm = np.einsum("tab,tjb->tja", c2w[:, :3, :3], in_camera) + c2w[:, None, :3, 3]
    world_from_sfm, floor = floor_frame(in_sfm, cameras.points * scale, c2w[0, :3, 2], cfg, rng)
    in_floor = in_sfm @ world_from_sfm[:3, :3].T + world_from_sfm[:3, 3]
    check = np.zeros(0)
    if not cameras.static and floor["floor_source"] == "scene points":  # a floor from the feet checks nothing
        check = ground_metrology(track.image, in_floor, np.array(_FEET_INDEX), world_from_sfm @ c2w,
                                 cameras.intrinsic)
    body["scale_check"] = round(float(np.median(check)), 3) if len(check) >= 3 else None
    landmarks, lean = upright(in_floor, cfg.upright_hip_share)
    floor["trunk_correction_deg"] = round(lean, 2)
    points = cameras.points * scale @ world_from_sfm[:3, :3].T + world_from_sfm[:3, 3]
    timings["align"] = time.perf_counter() - start

    start = time.perf_counter()
    model = build_humanoid()
    thigh, shin = leg_lengths(model)
    # Our bone lengths first, then the first pass's grounding: the landmarks then stand where the
    # humanoid does, and the hips can be lowered onto a seat without the feet moving.
    resampled = with_leg_lengths(resample_landmarks(fill_gaps(landmarks), fps, cfg.fps), thigh, shin)
    first = landmarks_to_motion(resampled, cfg.fps, model=model)
    resampled[..., 2] += first.ground_offset[:, None]
    found = find_seats(first.motion, points, cfg) if len(points) else []
    motion, gaps = settle(resampled, first.motion, found, cfg, model)
    seat_records = [{"bodies": list(s.bodies), "frames": [s.start, s.stop], "seat_top": round(s.top, 3),
                     "underside_above_seat": round(float(g), 3)} for s, g in zip(found, gaps)]
    body_pos = compute_kinematics(motion, model).body_pos
    soles = sole_points(model, motion.qpos())
    tops = [b for b in level_tops(points, body_pos[:, 0], cfg.planes) if not _passed_through(b, body_pos, soles)]
    boxes = [ground_box(points, body_pos[:, 0], cfg.planes), *tops, *(s.box for s in found)]
    timings["motion_and_planes"] = time.perf_counter() - start

    start = time.perf_counter()
    completion = contact_completion(motion, boxes, "kinematic", cfg.contact)
    timings["contact"] = time.perf_counter() - start

    flags, warn = quality_flags(track, cameras, scale, ratios, in_camera)
    tilted = floor_warning(floor, cameras, cfg.trunk_to_floor_warning_deg)
    if tilted is not None:
        warn.append(tilted)
    if body["scale_check"] is not None and abs(body["scale_check"] - 1.0) > cfg.scale_check_tolerance:
        warn.append(f"the scale disagrees with metrology against the floor: the scene is {body['scale_check']:.2f} "
                    f"times the size the person's height above it says (the floor or the camera solve is off)")
    camera_height = float(np.median((world_from_sfm @ c2w)[:, 2, 3]))
    flags |= floor | body | {"scale": round(scale, 6), "camera_height_m": round(camera_height, 3),
                             "seats": seat_records,
                             "cached": [name for name, hit in (("person", track_cached), ("cameras", cameras_cached))
                                        if hit]}
    for message in warn:
        warnings.warn(message, stacklevel=2)
    flags["warnings"] = warn
    return VideoReconstruction(boxes=boxes + list(completion.boxes), motion=motion, person=track, cameras=cameras,
                               scale=scale, world_from_sfm=world_from_sfm, landmarks=landmarks,
                               completion=completion, flags=flags, timings=timings)
