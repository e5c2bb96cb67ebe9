"""Reconstruction inputs: depth videos as :class:`~crisp_gym.reconstruct.frames.Frames`, and the human motion.

Depth videos (:func:`read_frames` picks the reader from the path):

* a MegaSAM-style ``.npz`` (:func:`read_megasam_npz`): ``depths`` (T, H, W), possibly float16
  and up to an unknown scale; ``intrinsic`` (3, 3); ``cam_c2w`` (T, 4, 4) (OpenCV camera →
  world); optional ``images`` (T, H, W, 3) uint8, ``masks`` (T, H, W) (person = 1) and ``fps``
  (else 30). A folder holding an ``input.npz`` (what ``crisp synth`` writes) reads that file.
* an RGB-D folder (:func:`read_rgbd_folder`) in the TUM layout (``rgb.txt`` and ``depth.txt``
  listing ``timestamp path``, 16-bit depth PNGs in units of 1/5000 m, optional
  ``groundtruth.txt`` with ``timestamp tx ty tz qx qy qz qw`` camera → world) or the Redwood
  layout (``color/`` or ``image/`` and ``depth/`` folders of images paired in numeric name order,
  16-bit PNG or PGM depth in mm, optional camera → world poses as a ``*.log`` trajectory of
  matrices or a ``pose.txt`` of ``tx ty tz qx qy qz qw`` lines, one per frame, as in the
  slambook2 examples). Intrinsics and depth scale come from :class:`RgbdFolderConfig`
  (``crisp reconstruct --intrinsics FX FY CX CY --depth-scale S``), else an
  ``intrinsic.json`` (Open3D's format: ``width``, ``height``, column-major
  ``intrinsic_matrix``, optional ``depth_scale``) or a ``camera.txt`` (``fx fy cx cy
  [depth_scale]``), else the layout's default camera (TUM freiburg1, or Open3D's PrimeSense
  default for Redwood), both given for 640×480 and scaled to the image size. Without poses
  the camera is tracked by Open3D's RGB-D odometry, frame to frame.

Human motion (:func:`read_motion`, for ``--motion``) comes back as a :class:`MotionInput`
that says which frame it is in: ``motion.npz`` and BVH are in a z-up world of their own;
GVHMR-style SMPL parameters (``global_orient``, ``body_pose`` (63 or 69), ``transl``; an npz, or
GVHMR's ``.pt`` results with ``smpl_params_incam``) are in the camera frame: OpenCV axes
(x right, y down, z forward), metres, frame ``t`` in camera ``t``'s frame as GVHMR's
``smpl_params_incam`` are (``frame="camera0"`` reads them as all in the first camera's frame
instead). :mod:`crisp_gym.reconstruct.align` brings a camera-frame motion into the world.
"""

from __future__ import annotations

import json
import logging
import pickle
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import imageio.v3 as iio
import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation, Slerp
from tqdm import tqdm

from crisp_gym.file_errors import reading
from crisp_gym.geometry import pixel_rays
from crisp_gym.motion import Motion
from crisp_gym.npz import read_npz
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.smpl import load_smpl_params, write_smpl_npz

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0
"""Frame rate assumed when an input does not say."""

TUM_FR1_INTRINSIC = (517.3, 516.5, 318.6, 255.3)
"""fx, fy, cx, cy of the TUM RGB-D freiburg1 colour camera at 640×480 (the TUM benchmark's calibration)."""

PRIMESENSE_INTRINSIC = (525.0, 525.0, 319.5, 239.5)
"""fx, fy, cx, cy of Open3D's ``PrimeSenseDefault`` at 640×480 (the Redwood datasets' camera)."""

TUM_DEPTH_SCALE = 5000.0
"""TUM depth PNG units per metre."""

REDWOOD_DEPTH_SCALE = 1000.0
"""Redwood depth PNG units per metre (millimetres)."""

SMPL_PELVIS_OFFSET = (0.0, -0.223, 0.028)
"""SMPL's rest pelvis joint relative to the model origin for the mean shape (m, SMPL axes: y up,
z forward), approximately. SMPL rotates the body about this joint, so the pelvis is at
``transl + offset`` in the parameters' frame; a body shape other than the mean moves it by a few cm."""

MotionFrame = Literal["world", "camera", "camera0"]

_SMPL_KEYS = ("global_orient", "body_pose", "transl")


# --------------------------------------------------------------------------- MegaSAM npz


def read_megasam_npz(path: str | Path) -> Frames:
    """A MegaSAM-style npz as :class:`Frames` (keys in the module docstring)."""
    path = Path(path)
    data = read_npz(path, "MegaSAM-style npz (depths, intrinsic, cam_c2w)")
    missing = [k for k in ("depths", "intrinsic", "cam_c2w") if k not in data]
    if missing:
        raise ValueError(f"{path} lacks {missing}; a MegaSAM-style npz holds depths (T, H, W), intrinsic (3, 3), "
                         f"cam_c2w (T, 4, 4) and optionally images, masks, fps; found {sorted(data)}")
    depths = data["depths"]
    if depths.ndim != 3 or not np.issubdtype(depths.dtype, np.floating):
        raise ValueError(f"{path}: depths must be a float (T, H, W) array, got {depths.dtype} {depths.shape}")
    t, h, w = depths.shape
    intrinsic = np.asarray(data["intrinsic"], dtype=np.float64)
    if intrinsic.shape != (3, 3):
        raise ValueError(f"{path}: intrinsic must be (3, 3), got {intrinsic.shape}")
    poses = np.asarray(data["cam_c2w"], dtype=np.float64)
    if poses.shape != (t, 4, 4):
        raise ValueError(f"{path}: cam_c2w must be ({t}, 4, 4) to match depths {depths.shape}, got {poses.shape}")
    bad = ~np.isfinite(poses).all(axis=(1, 2))
    if bad.any():
        raise ValueError(f"{path}: cam_c2w has NaN or infinite values in {int(bad.sum())} frames "
                         f"(first: frame {int(np.argmax(bad))})")
    rgb = data.get("images")
    if rgb is not None and (rgb.shape != (t, h, w, 3) or rgb.dtype != np.uint8):
        raise ValueError(f"{path}: images must be uint8 ({t}, {h}, {w}, 3), got {rgb.dtype} {rgb.shape}")
    masks = data.get("masks")
    if masks is not None:
        if masks.shape != (t, h, w):
            raise ValueError(f"{path}: masks must be ({t}, {h}, {w}) with person = 1, got {masks.shape}")
        masks = masks > 0.5 if np.issubdtype(masks.dtype, np.floating) else masks.astype(bool)
    fps = float(np.asarray(data["fps"]).reshape(())) if "fps" in data else DEFAULT_FPS
    try:
        return Frames(depth=depths, intrinsic=intrinsic, cam_c2w=poses, fps=fps, rgb=rgb, person_mask=masks)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


# --------------------------------------------------------------------------- RGB-D folders


@dataclass(frozen=True)
class RgbdFolderConfig:
    """Reading an RGB-D folder and, when it has no poses, tracking the camera.

    Attributes:
        intrinsics: (fx, fy, cx, cy) of the depth images in pixels, overriding the folder's
            ``intrinsic.json`` / ``camera.txt`` and the layout's default.
        depth_scale: depth image units per metre (1000 for millimetres), overriding the same.
        max_time_difference: TUM colour and depth frames farther apart than this (s) are not
            paired (the TUM tools' default).
        depth_min, depth_max: depths the odometry uses (m); Open3D's default maximum of 4 m is
            the range where a structured-light sensor's depth is reliable.
        depth_diff_max: largest depth difference of corresponding pixels the odometry accepts (m,
            Open3D's default).
        max_failures: largest fraction of frame pairs whose odometry may fail (each failure
            repeats the previous frame-to-frame motion) before the folder is rejected.
        min_pair_agreement: a pair whose odometry "succeeded" has failed all the same when fewer
            than this share of the pixels the two frames should both see agree in depth (within
            5 %) once moved by it (true poses of a real room give 0.7-0.96; odometry that lost
            track, 0.08-0.19).
    """

    intrinsics: tuple[float, float, float, float] | None = None
    depth_scale: float | None = None
    max_time_difference: float = 0.02
    depth_min: float = 0.1
    depth_max: float = 4.0
    depth_diff_max: float = 0.03
    max_failures: float = 0.1
    min_pair_agreement: float = 0.5


def _read_list(path: Path, values: int = 1) -> list[tuple[float, list[str]]]:
    """``timestamp value...`` lines (at least ``values`` values) of a TUM text file, comments skipped."""
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            stamp = float(parts[0])
        except ValueError:
            stamp = np.nan
        if not np.isfinite(stamp) or len(parts) < 1 + values:
            raise ValueError(f"{path}:{number}: expected a timestamp and {values} value(s), got {line!r}")
        rows.append((stamp, parts[1:]))
    if not rows:
        raise ValueError(f"{path} lists no frames")
    return rows


def _pair_by_time(depth_times: np.ndarray, rgb_times: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """(depth index, rgb index) pairs of nearest timestamps within ``max_dt``, each used once."""
    order = np.argsort(rgb_times)
    sorted_rgb = rgb_times[order]
    pos = np.clip(np.searchsorted(sorted_rgb, depth_times), 1, len(sorted_rgb) - 1) if len(sorted_rgb) > 1 \
        else np.zeros(len(depth_times), int)
    left, right = np.maximum(pos - 1, 0), pos
    nearest = np.where(np.abs(sorted_rgb[left] - depth_times) <= np.abs(sorted_rgb[right] - depth_times), left, right)
    dt = np.abs(sorted_rgb[nearest] - depth_times)
    pairs: dict[int, tuple[float, int]] = {}
    for i in np.flatnonzero(dt <= max_dt):
        j = int(order[nearest[i]])
        if j not in pairs or dt[i] < pairs[j][0]:
            pairs[j] = (float(dt[i]), int(i))
    return sorted((i, j) for j, (_, i) in pairs.items())


def _tum_poses(path: Path, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera → world poses interpolated at ``times`` and which times the trajectory covers."""
    rows = _read_list(path, values=7)
    stamps = np.array([r[0] for r in rows])
    try:
        values = np.array([[float(x) for x in r[1][:7]] for r in rows])
    except ValueError:
        raise ValueError(f"{path}: expected 'timestamp tx ty tz qx qy qz qw' lines") from None
    if values.shape[1] != 7:
        raise ValueError(f"{path}: expected 'timestamp tx ty tz qx qy qz qw' lines")
    order = np.argsort(stamps)
    stamps, values = stamps[order], values[order]
    inside = (times >= stamps[0]) & (times <= stamps[-1])
    t = times[inside]
    translation = np.stack([np.interp(t, stamps, values[:, i]) for i in range(3)], axis=1)
    if len(stamps) > 1:
        rotation = Slerp(stamps, Rotation.from_quat(values[:, 3:7]))(t)
    else:
        rotation = Rotation.from_quat(np.repeat(values[:1, 3:7], len(t), axis=0))
    return _pose_matrices(translation, rotation), inside


def _pose_matrices(translation: np.ndarray, rotation: Rotation) -> np.ndarray:
    """(N, 4, 4) camera → world matrices from (N, 3) positions and N rotations."""
    poses = np.tile(np.eye(4), (len(translation), 1, 1))
    poses[:, :3, 3] = translation
    poses[:, :3, :3] = rotation.as_matrix()
    return poses


def _natural_key(path: Path) -> tuple:
    """Sort key that orders ``2.png`` before ``10.png``."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.stem))


def _pose_lines(path: Path, count: int) -> np.ndarray:
    """(count, 4, 4) camera → world poses from ``tx ty tz qx qy qz qw`` lines, one per frame in order."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    try:
        values = np.array([[float(x) for x in row] for row in rows])
    except ValueError:
        raise ValueError(f"{path}: expected one 'tx ty tz qx qy qz qw' line per frame") from None
    if values.ndim != 2 or values.shape != (count, 7):
        raise ValueError(f"{path}: expected {count} lines 'tx ty tz qx qy qz qw' (one per frame), "
                         f"got {len(rows)} lines of {values.shape[1] if values.ndim == 2 else '?'} numbers")
    return _pose_matrices(values[:, :3], Rotation.from_quat(values[:, 3:]))


def _folder_camera(folder: Path, default: tuple[float, float, float, float], default_scale: float,
                   width: int, height: int) -> tuple[np.ndarray, float]:
    """(K, depth units per metre) from ``intrinsic.json`` / ``camera.txt``, else the scaled default."""
    json_path, txt_path = folder / "intrinsic.json", folder / "camera.txt"
    if json_path.is_file():
        try:
            info = json.loads(json_path.read_text())
            k = np.asarray(info["intrinsic_matrix"], dtype=np.float64).reshape(3, 3).T  # column-major
            size = (int(info["width"]), int(info["height"]))
        except (KeyError, ValueError, TypeError, json.JSONDecodeError) as err:
            raise ValueError(f"{json_path}: expected Open3D's intrinsic JSON (width, height, column-major "
                             f"intrinsic_matrix of 9 numbers): {err}") from None
        if size != (width, height):
            raise ValueError(f"{json_path} is for {size[0]}x{size[1]} images but the depth images are {width}x{height}")
        return k, float(info.get("depth_scale", default_scale))
    if txt_path.is_file():
        lines = [ln.split() for ln in txt_path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
        try:
            numbers = [float(x) for x in lines[0]]
        except (IndexError, ValueError):
            numbers = []
        if len(numbers) not in (4, 5):
            raise ValueError(f"{txt_path}: expected one line 'fx fy cx cy [depth_scale]'")
        fx, fy, cx, cy = numbers[:4]
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), numbers[4] if len(numbers) == 5 else default_scale
    fx, fy, cx, cy = default
    sx, sy = width / 640.0, height / 480.0
    return np.array([[fx * sx, 0, (cx + 0.5) * sx - 0.5], [0, fy * sy, (cy + 0.5) * sy - 0.5], [0, 0, 1.0]]), \
        default_scale


def _read_image(path: Path, what: str) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"the {what} image {path} is missing")
    try:
        return iio.imread(path)
    except Exception as err:  # noqa: BLE001 - any decoder failure is a damaged or foreign file
        reason = (str(err).strip().splitlines() or [""])[0]  # imageio's own messages run over many lines
        raise ValueError(f"the {what} image {path} cannot be read ({type(err).__name__}: {reason})") from None


def _load_images(color_paths: list[Path], depth_paths: list[Path], depth_scale: float,
                 progress: bool) -> tuple[np.ndarray, np.ndarray]:
    depth, rgb = [], []
    for c, d in tqdm(list(zip(color_paths, depth_paths)), desc="read", unit="frame", disable=not progress):
        raw = _read_image(d, "depth")
        # 16-bit PGMs read as int32: any single-channel integer image within 16 bits is a depth image
        if raw.ndim != 2 or not np.issubdtype(raw.dtype, np.integer) or raw.min() < 0 or raw.max() > 65535:
            raise ValueError(f"{d}: depth images must be single-channel 16-bit PNGs or PGMs, "
                             f"got {raw.dtype} {raw.shape}")
        colour = _read_image(c, "colour")
        if colour.ndim == 2:
            colour = np.repeat(colour[..., None], 3, axis=2)
        colour = colour[..., :3]
        if colour.shape[:2] != raw.shape or colour.dtype != np.uint8:
            raise ValueError(f"{c}: colour must be 8-bit and the depth image's size {raw.shape}, "
                             f"got {colour.dtype} {colour.shape}")
        depth.append(raw.astype(np.float32) / np.float32(depth_scale))
        rgb.append(colour)
    return np.stack(depth), np.stack(rgb)


def depth_agreement(depth: np.ndarray, intrinsic: np.ndarray, cam_c2w: np.ndarray, k: int, j: int,
                    stride: int = 4, tolerance: float = 0.05) -> float:
    """Of frame ``k``'s pixels (every ``stride``-th) that land on a valid pixel of frame ``j`` when
    moved by the poses ``cam_c2w``, the share whose depth there agrees within ``tolerance``
    (relative): near 1 for right poses, low for wrong ones."""
    h, w = depth.shape[1:]
    z = depth[k, ::stride, ::stride]
    valid = z > 0
    rays = pixel_rays(intrinsic, w, h)[::stride, ::stride][valid] * z[valid, None]
    j_from_k = np.linalg.inv(cam_c2w[j]) @ cam_c2w[k]
    cam = rays @ j_from_k[:3, :3].T + j_from_k[:3, 3]
    front = cam[:, 2] > 1e-3
    cam = cam[front]
    px = np.round(cam[:, 0] / cam[:, 2] * intrinsic[0, 0] + intrinsic[0, 2]).astype(int)
    py = np.round(cam[:, 1] / cam[:, 2] * intrinsic[1, 1] + intrinsic[1, 2]).astype(int)
    inside = (px >= 0) & (px < w) & (py >= 0) & (py < h)
    there = depth[j, py[inside], px[inside]]
    seen = there > 0
    if not seen.any():
        return 0.0
    return float(np.mean(np.abs(there[seen] - cam[inside, 2][seen]) < tolerance * cam[inside, 2][seen]))


def rgbd_odometry(depth: np.ndarray, rgb: np.ndarray, intrinsic: np.ndarray, config: RgbdFolderConfig | None = None,
                  progress: bool = True) -> np.ndarray:
    """(T, 4, 4) camera → world poses (first camera = world) chained from Open3D's frame-to-frame
    RGB-D odometry (hybrid photometric and geometric term).

    Each pair starts from the previous pair's motion (a constant-velocity guess); a failed pair
    (no convergence, or a motion the pair's depth does not agree with, :func:`depth_agreement`)
    repeats it. More than ``config.max_failures`` failed pairs raise a ``ValueError``.
    """
    cfg = config or RgbdFolderConfig()
    t, h, w = depth.shape
    camera = o3d.camera.PinholeCameraIntrinsic(w, h, intrinsic[0, 0], intrinsic[1, 1], intrinsic[0, 2], intrinsic[1, 2])
    option = o3d.pipelines.odometry.OdometryOption(depth_diff_max=cfg.depth_diff_max, depth_min=cfg.depth_min,
                                                   depth_max=cfg.depth_max)
    jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def rgbd(k: int) -> o3d.geometry.RGBDImage:
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(rgb[k])), o3d.geometry.Image(np.ascontiguousarray(depth[k])),
            depth_scale=1.0, depth_trunc=cfg.depth_max, convert_rgb_to_intensity=True)

    poses = np.tile(np.eye(4), (t, 1, 1))
    motion = np.eye(4)  # camera k-1 ← camera k
    failures = 0
    target = rgbd(0)
    for k in tqdm(range(1, t), desc="odometry", unit="frame", disable=not progress):
        source = rgbd(k)
        ok, trans, _ = o3d.pipelines.odometry.compute_rgbd_odometry(source, target, camera, motion, jacobian, option)
        if not ok:
            ok, trans, _ = o3d.pipelines.odometry.compute_rgbd_odometry(source, target, camera, np.eye(4),
                                                                        jacobian, option)
        if ok:  # converged; to a motion the two frames' depth contradicts, it failed all the same
            pair = np.stack([np.eye(4), trans])
            ok = depth_agreement(depth[k - 1:k + 1], intrinsic, pair, 1, 0) >= cfg.min_pair_agreement
        if ok:
            motion = trans
        else:
            failures += 1
        poses[k] = poses[k - 1] @ motion
        target = source
    if failures > cfg.max_failures * max(t - 1, 1):
        raise ValueError(f"RGB-D odometry failed on {failures} of {t - 1} frame pairs (no convergence, or a motion "
                         f"under which fewer than {cfg.min_pair_agreement:.0%} of the overlapping pixels agree in "
                         "depth); the folder needs a trajectory (groundtruth.txt, pose.txt or *.log), or frames with more "
                         "overlap and texture")
    if failures:
        log.warning("RGB-D odometry failed on %d of %d frame pairs (constant motion assumed there)", failures, t - 1)
    return poses


_ROOM_DEPTH = (0.5, 8.0)  # m: median depths of an RGB-D sensor looking at a room or a person in it


def _check_depth_range(folder: Path, depth: np.ndarray, depth_scale: float) -> None:
    """Warn when the median depth is no room's: the usual cause is a wrong depth scale (TUM's
    1/5000 m applied to millimetres gives a 3 m room as 0.6 m), which fits tiny boxes silently."""
    valid = depth[depth > 0]
    if not valid.size:
        raise ValueError(f"{folder}: every depth pixel is 0 (no measurement)")
    median = float(np.median(valid))
    if _ROOM_DEPTH[0] <= median <= _ROOM_DEPTH[1]:
        return
    hints = [f"{scale:g} ({name}: median {median * depth_scale / scale:.2f} m)"
             for name, scale in (("millimetres", 1000.0), ("TUM's 1/5000 m", 5000.0))
             if scale != depth_scale and _ROOM_DEPTH[0] <= median * depth_scale / scale <= _ROOM_DEPTH[1]]
    log.warning("%s: the median depth is %.2f m with %g depth units per metre, outside a room's %g-%g m; "
                "is the depth scale right?%s", folder, median, depth_scale, *_ROOM_DEPTH,
                f" --depth-scale {' or '.join(hints)}" if hints else "")


def read_rgbd_folder(path: str | Path, config: RgbdFolderConfig | None = None, progress: bool = True) -> Frames:
    """A TUM- or Redwood-layout RGB-D folder as metric :class:`Frames` (see the module docstring)."""
    cfg = config or RgbdFolderConfig()
    folder = Path(path)
    if not folder.is_dir():
        raise FileNotFoundError(f"no RGB-D folder at {folder}")
    poses: np.ndarray | None = None
    fps = DEFAULT_FPS
    if (folder / "depth.txt").is_file() and (folder / "rgb.txt").is_file():
        depth_rows, rgb_rows = _read_list(folder / "depth.txt"), _read_list(folder / "rgb.txt")
        depth_times = np.array([r[0] for r in depth_rows])
        pairs = _pair_by_time(depth_times, np.array([r[0] for r in rgb_rows]), cfg.max_time_difference)
        if not pairs:
            raise ValueError(f"{folder}: no colour frame within {cfg.max_time_difference} s of any depth frame")
        times = depth_times[[i for i, _ in pairs]]
        depth_paths = [folder / depth_rows[i][1][0] for i, _ in pairs]
        color_paths = [folder / rgb_rows[j][1][0] for _, j in pairs]
        if (folder / "groundtruth.txt").is_file():
            poses, inside = _tum_poses(folder / "groundtruth.txt", times)
            if not inside.any():
                raise ValueError(f"{folder}/groundtruth.txt covers none of the frames' timestamps")
            if not inside.all():
                log.warning("%s: %d frames outside the ground-truth trajectory's time span are dropped",
                            folder, int((~inside).sum()))
            depth_paths = [p for p, keep in zip(depth_paths, inside) if keep]
            color_paths = [p for p, keep in zip(color_paths, inside) if keep]
            times = times[inside]
        if len(times) > 1:
            fps = float(1.0 / np.median(np.diff(times)))
        default, default_scale = TUM_FR1_INTRINSIC, TUM_DEPTH_SCALE
    elif (folder / "depth").is_dir():
        colour_dir = next((folder / n for n in ("color", "image", "rgb") if (folder / n).is_dir()), None)
        if colour_dir is None:
            raise ValueError(f"{folder}: a Redwood-layout folder needs color/ (or image/) next to depth/")
        depth_paths = sorted((p for p in (folder / "depth").iterdir() if p.suffix.lower() in (".png", ".pgm")),
                             key=_natural_key)
        color_paths = sorted((p for p in colour_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg")),
                             key=_natural_key)
        if not depth_paths or len(depth_paths) != len(color_paths):
            raise ValueError(f"{folder}: depth/ has {len(depth_paths)} PNG/PGM images and {colour_dir.name}/ "
                             f"{len(color_paths)} images; they must pair one to one (and not be empty)")
        logs = sorted(folder.glob("*.log"))
        if (folder / "pose.txt").is_file():
            poses = _pose_lines(folder / "pose.txt", len(depth_paths))
        elif logs:
            trajectory = o3d.io.read_pinhole_camera_trajectory(str(logs[0]))
            if len(trajectory.parameters) != len(depth_paths):
                raise ValueError(f"{logs[0]} has {len(trajectory.parameters)} poses for {len(depth_paths)} frames")
            poses = np.stack([np.linalg.inv(p.extrinsic) for p in trajectory.parameters])
        default, default_scale = PRIMESENSE_INTRINSIC, REDWOOD_DEPTH_SCALE
    else:
        raise ValueError(f"{folder} is neither a TUM folder (rgb.txt, depth.txt) nor a Redwood folder "
                         "(color/ and depth/)")
    first = _read_image(depth_paths[0], "depth")
    intrinsic, depth_scale = _folder_camera(folder, default, default_scale, first.shape[1], first.shape[0])
    if cfg.intrinsics is not None:
        fx, fy, cx, cy = cfg.intrinsics
        intrinsic = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    if cfg.depth_scale is not None:
        if not (np.isfinite(cfg.depth_scale) and cfg.depth_scale > 0):
            raise ValueError(f"the depth scale must be a positive number of units per metre, got {cfg.depth_scale}")
        depth_scale = cfg.depth_scale
    depth, rgb = _load_images(color_paths, depth_paths, depth_scale, progress)
    _check_depth_range(folder, depth, depth_scale)
    if poses is None:
        poses = rgbd_odometry(depth, rgb, intrinsic, cfg, progress)
    try:
        return Frames(depth=depth, intrinsic=intrinsic, cam_c2w=poses, fps=fps, rgb=rgb)
    except ValueError as err:
        raise ValueError(f"{folder}: {err}") from None


def read_frames(path: str | Path, progress: bool = True, rgbd: RgbdFolderConfig | None = None) -> Frames:
    """Any supported depth video: an npz file, a folder holding ``input.npz``, or an RGB-D folder
    (read with ``rgbd``)."""
    path = Path(path)
    if path.is_file():
        if path.suffix.lower() != ".npz":
            raise ValueError(f"{path}: a depth-video file must be a MegaSAM-style .npz")
        with reading(path, "MegaSAM-style npz"):
            return read_megasam_npz(path)
    if path.is_dir():
        with reading(path, "depth video folder"):
            if (path / "input.npz").is_file():
                return read_megasam_npz(path / "input.npz")
            return read_rgbd_folder(path, rgbd, progress=progress)
    raise FileNotFoundError(f"no depth video at {path} (expected an .npz or an RGB-D folder)")


# --------------------------------------------------------------------------- plain video

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")


def _image_files(folder: Path) -> list[Path]:
    return sorted((f for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)


def is_plain_video(path: str | Path) -> bool:
    """A video file, or a folder of images with no depth (not an RGB-D or MegaSAM input)."""
    path = Path(path)
    if path.is_file():
        return path.suffix.lower() in VIDEO_SUFFIXES
    if not path.is_dir() or (path / "input.npz").is_file() or (path / "rgb.txt").is_file():
        return False
    return not (path / "depth").is_dir() and bool(_image_files(path))


VIDEO_FPS_RANGE = (1.0, 1000.0)
"""Frame rates a video can have (frames per second): below one frame a second there is no motion
to follow, above a thousand the header is wrong."""


def check_video_fps(rate: float, what: str) -> float:
    """``rate`` if it lies in :data:`VIDEO_FPS_RANGE`, else a ValueError naming ``what``."""
    low, high = VIDEO_FPS_RANGE
    if not (np.isfinite(rate) and low <= rate <= high):
        raise ValueError(f"{what}: a video's frame rate must be in [{low:g}, {high:g}] fps, got {rate:g}")
    return float(rate)


def read_video(path: str | Path, max_side: int = 960, fps: float | None = None, max_frames: int = 1800,
               progress: bool = True) -> tuple[np.ndarray, float]:
    """(T, H, W, 3) uint8 RGB frames of a video file or an image folder, downscaled so the long
    side is at most ``max_side``, and the frame rate (a file's own; an image folder's is ``fps``,
    else :data:`DEFAULT_FPS` with a warning). More than ``max_frames`` frames is an error: the frames
    are held in memory (1,800 at 960×540 take 2.8 GB)."""
    import cv2  # noqa: PLC0415 - only this reader needs it

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no video at {path}")
    if fps is not None:
        check_video_fps(fps, "--fps")
    if path.is_dir():
        files = _image_files(path)
        if not files:
            raise ValueError(f"{path} holds no images ({', '.join(IMAGE_SUFFIXES)})")
        if fps is None:
            log.warning("%s: an image folder has no frame rate; assuming %.0f fps (pass --fps)", path, DEFAULT_FPS)
        rate = float(fps or DEFAULT_FPS)
        if len(files) > max_frames:
            raise ValueError(f"{path} has {len(files)} images, more than {max_frames}; trim it first")
        source = (_read_image(f, "image") for f in files)
        total = len(files)
    else:
        if path.suffix.lower() not in VIDEO_SUFFIXES:
            raise ValueError(f"{path}: not a video file ({', '.join(VIDEO_SUFFIXES)})")
        try:
            meta = iio.immeta(path)
        except Exception as err:  # noqa: BLE001 - any decoder failure is an unreadable file
            raise ValueError(f"{path}: cannot read the video ({err})") from None
        rate = check_video_fps(float(fps or meta.get("fps") or DEFAULT_FPS),
                               f"{path} (pass --fps if its header is wrong)")
        total = None
        source = iio.imiter(path)
    frames = []
    for image in tqdm(source, total=total, desc="frames", unit="frame", disable=not progress):
        image = np.asarray(image)
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        image = image[..., :3].astype(np.uint8)
        scale = max_side / max(image.shape[:2])
        if scale < 1:
            image = cv2.resize(image, (round(image.shape[1] * scale), round(image.shape[0] * scale)),
                               interpolation=cv2.INTER_AREA)
        if frames and image.shape != frames[0].shape:
            raise ValueError(f"{path}: frame {len(frames)} is {image.shape[:2]}, the first {frames[0].shape[:2]}")
        frames.append(image)
        if len(frames) > max_frames:
            raise ValueError(f"{path} has more than {max_frames} frames; trim it first")
    if len(frames) < 2:
        raise ValueError(f"{path}: a video needs at least 2 frames, got {len(frames)}")
    return np.stack(frames), rate


# --------------------------------------------------------------------------- human motion


@dataclass(frozen=True)
class MotionInput:
    """A human motion and the frame it is expressed in.

    Attributes:
        motion: the humanoid motion (metres).
        frame: ``"world"`` (a z-up world unrelated to the video), ``"camera"`` (frame t in camera
            t's OpenCV frame, as GVHMR's ``smpl_params_incam``) or ``"camera0"`` (every frame in
            the first camera's OpenCV frame).
        source: the file it was read from.
    """

    motion: Motion
    frame: MotionFrame
    source: str = ""

    def __post_init__(self) -> None:
        if self.frame not in ("world", "camera", "camera0"):
            raise ValueError(f"frame must be 'world', 'camera' or 'camera0', got {self.frame!r}")


def _read_smpl_source(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a motion npz, or flat SMPL parameter arrays from a GVHMR ``.pt``
    (``smpl_params_incam`` preferred)."""
    if path.suffix.lower() == ".npz":
        return read_npz(path, "motion npz (motion.npz or SMPL parameters)")
    import torch

    try:
        content = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, OSError, EOFError, ValueError, pickle.UnpicklingError) as err:
        raise ValueError(f"{path} is not a readable torch file of tensors ({err})") from None
    if isinstance(content, dict) and isinstance(content.get("smpl_params_incam"), dict):
        content = content["smpl_params_incam"]
    if not isinstance(content, dict):
        raise ValueError(f"{path} must hold a dict of SMPL parameters (or GVHMR's results with smpl_params_incam)")
    return {k: np.asarray(v.numpy() if hasattr(v, "numpy") else v) for k, v in content.items()}


def read_motion(path: str | Path, *, fps: float | None = None, up_axis: str = "y",
                frame: MotionFrame = "camera", pelvis_offset=SMPL_PELVIS_OFFSET) -> MotionInput:
    """A human motion for ``--motion``: ``motion.npz``, BVH, or camera-frame SMPL parameters.

    ``fps`` overrides the file's frame rate (SMPL files without ``fps`` default to 30);
    ``up_axis`` is a BVH's up axis. SMPL parameters are read as camera-frame (``frame`` is
    ``"camera"`` or ``"camera0"``, see :class:`MotionInput`) with the pelvis at
    ``transl + pelvis_offset`` (:data:`SMPL_PELVIS_OFFSET`); they are not grounded, since the
    floor is not known yet.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no motion file at {path}")
    suffix = path.suffix.lower()
    if suffix == ".bvh":
        from crisp_gym.bvh import load_bvh

        return MotionInput(load_bvh(path, up_axis=up_axis, target_fps=fps), "world", str(path))
    if suffix not in (".npz", ".pt", ".pth"):
        raise ValueError(f"{path}: unsupported motion file {suffix!r}; expected motion.npz, .bvh, or SMPL "
                         "parameters (.npz / GVHMR .pt)")
    params = _read_smpl_source(path)
    if "dof_pos" in params:
        motion = Motion.load(path)
        return MotionInput(motion.resample(fps) if fps else motion, "world", str(path))
    if frame not in ("camera", "camera0"):
        raise ValueError("SMPL parameters are read in a camera frame: frame must be 'camera' or 'camera0', "
                         f"got {frame!r}")
    missing = [k for k in _SMPL_KEYS if k not in params]
    if missing:
        raise ValueError(f"{path}: an npz motion needs motion.npz keys (dof_pos, ...) or SMPL keys "
                         f"{list(_SMPL_KEYS)}; missing {missing}, found {sorted(params)}")
    offset = np.asarray(pelvis_offset, dtype=float)
    if offset.shape != (3,):
        raise ValueError(f"pelvis_offset must have 3 entries, got {offset.shape}")
    params = dict(params)
    transl = np.asarray(params["transl"], dtype=float)
    if transl.ndim == 2 and transl.shape[1] == 3:
        params["transl"] = transl + offset
    try:
        motion = load_smpl_params(params, fps=fps, up_axis="z", to_floor=False)  # "z": keep the camera's axes
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
    return MotionInput(motion, frame, str(path))


def save_camera_smpl(motion: Motion, path: str | Path, pelvis_offset=SMPL_PELVIS_OFFSET) -> Path:
    """Write a camera-frame ``motion`` as GVHMR-style SMPL parameters (the inverse of :func:`read_motion`).

    ``global_orient`` (T, 3) and ``body_pose`` (T, 69) axis-angle, ``transl`` (T, 3) = pelvis −
    ``pelvis_offset``, ``fps``; all in the motion's (camera) frame. Written atomically.
    """
    return write_smpl_npz(path, motion, pelvis_offset=pelvis_offset)
