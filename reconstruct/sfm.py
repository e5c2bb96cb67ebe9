"""Camera poses and scene points of a plain video: COLMAP (``pycolmap``, CPU) on the person-masked frames.

A handheld clip of a person barely moves the camera (the bundled real video: 6 cm, 4.6°), and
COLMAP's defaults then build no model at all. The settings here (:class:`SfmConfig`, measured on
that clip: 64/64 frames registered, 0.24 px error) relax the initial pair's triangulation angle
and accept nearly homographic pairs, and give the focal length a prior instead of guessing it.

The result is up to scale (:mod:`crisp_gym.reconstruct.video` takes it from the person). When too few
frames register, :func:`solve_cameras` returns a fixed camera with the reason, and the scene then
comes from the person alone.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp
from tqdm import tqdm


@dataclass(frozen=True)
class SfmConfig:
    """Structure-from-motion settings.

    Attributes:
        max_frames: frames given to COLMAP, evenly spaced over the video (the others are
            interpolated): the mapping time grows with the observations.
        focal_factor: the focal-length prior in pixels per pixel of the image's long side (0.7:
            a phone's main camera, about 70° across the long side).
        refine_focal: let bundle adjustment refine the focal length from the prior. With it
            fixed at a wrong prior, the reconstruction of a small-baseline video comes out sheared
            (on the bundled real video: the ground tilted 40° against the standing person; refined
            from 672 to 843 px, 3.5°).
        max_features: SIFT features per frame.
        mask_dilation_px: the person's mask is grown by this before features are masked out
            (a moving person breaks the static-scene assumption).
        init_min_tri_angle, min_tri_angle: degrees, for the initial pair and for points.
        ransac_max_error: pixels, two-view geometry and registration.
        max_homography_inlier_ratio: pairs explained by a homography up to this share still count
            as general motion (COLMAP's 0.8 rejects a nearly rotating camera).
        min_registered_share: fewer registered frames than this share is a failure.
        max_mapping_seconds: COLMAP's mapping stops after this long (a camera that barely moves
            relative to its scene, e.g. a tripod's, keeps it trying new initial pairs for minutes).
        seed: COLMAP's random seed.
    """

    max_frames: int = 64
    focal_factor: float = 0.7
    refine_focal: bool = True
    max_features: int = 4096
    mask_dilation_px: int = 15
    init_min_tri_angle: float = 2.0
    min_tri_angle: float = 0.3
    ransac_max_error: float = 1.0
    max_homography_inlier_ratio: float = 0.95
    min_registered_share: float = 0.5
    max_mapping_seconds: float = 150.0
    seed: int = 0


@dataclass(frozen=True)
class CameraSolve:
    """Cameras for every frame and the static scene's points, in SfM units.

    Attributes:
        intrinsic: (3, 3) pinhole matrix.
        cam_c2w: (T, 4, 4) camera-to-world (OpenCV camera), interpolated between keyframes.
        keyframes: indices of the frames given to COLMAP.
        registered: (len(keyframes),) bool, registered by COLMAP.
        points: (N, 3) scene points; ``colors`` (N, 3) uint8.
        visible: per keyframe, the indices of the points it observes (empty if unregistered).
        reprojection_error: mean, pixels (NaN for a fixed camera).
        static: no usable SfM; ``cam_c2w`` is the identity and ``points`` empty.
        reason: why the camera is static ("" otherwise).
        seconds: time per step.
    """

    intrinsic: np.ndarray
    cam_c2w: np.ndarray
    keyframes: np.ndarray
    registered: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    visible: list[np.ndarray]
    reprojection_error: float
    static: bool = False
    reason: str = ""
    seconds: dict[str, float] = field(default_factory=dict)

    def baseline(self) -> float:
        """Largest distance of a camera centre from the first one (SfM units)."""
        centres = self.cam_c2w[:, :3, 3]
        return float(np.linalg.norm(centres - centres[0], axis=1).max())

    def rotation_deg(self) -> float:
        """Largest camera rotation from the first frame, degrees."""
        rel = Rotation.from_matrix(self.cam_c2w[0, :3, :3]).inv() * Rotation.from_matrix(self.cam_c2w[:, :3, :3])
        return float(np.rad2deg(rel.magnitude().max()))


def prior_intrinsic(height: int, width: int, focal_factor: float) -> np.ndarray:
    f = focal_factor * max(height, width)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def static_camera(num_frames: int, intrinsic: np.ndarray, reason: str,
                  seconds: dict[str, float] | None = None) -> CameraSolve:
    """A camera that never moves, with no scene points (the scene comes from the person);
    ``seconds``: the time spent finding that out."""
    return CameraSolve(intrinsic=intrinsic, cam_c2w=np.tile(np.eye(4), (num_frames, 1, 1)),
                       keyframes=np.zeros(0, int), registered=np.zeros(0, bool), points=np.zeros((0, 3)),
                       colors=np.zeros((0, 3), np.uint8), visible=[], reprojection_error=float("nan"),
                       static=True, reason=reason, seconds=dict(seconds or {}))


def _interpolate(num_frames: int, frames: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Camera poses at every frame from poses at ``frames`` (sorted): slerp and lerp, held at the ends."""
    t = np.clip(np.arange(num_frames), frames[0], frames[-1])
    out = np.tile(np.eye(4), (num_frames, 1, 1))
    if len(frames) == 1:
        out[:] = c2w[0]
        return out
    out[:, :3, :3] = Slerp(frames, Rotation.from_matrix(c2w[:, :3, :3]))(t).as_matrix()
    for axis in range(3):
        out[:, axis, 3] = np.interp(t, frames, c2w[:, axis, 3])
    return out


def _write_inputs(folder: Path, frames: np.ndarray, masks: np.ndarray, keyframes: np.ndarray,
                  dilation: int) -> list[str]:
    (folder / "images").mkdir()
    (folder / "masks").mkdir()
    kernel = np.ones((2 * dilation + 1, 2 * dilation + 1), np.uint8)
    names = []
    for k in keyframes:
        name = f"{k:06d}.png"
        cv2.imwrite(str(folder / "images" / name), cv2.cvtColor(frames[k], cv2.COLOR_RGB2BGR))
        person = cv2.dilate(masks[k].astype(np.uint8), kernel)
        cv2.imwrite(str(folder / "masks" / f"{name}.png"), (1 - person) * 255)  # COLMAP: 0 = ignore
        names.append(name)
    return names


def solve_cameras(frames: np.ndarray, masks: np.ndarray, config: SfmConfig | None = None,
                  progress: bool = True) -> CameraSolve:
    """COLMAP incremental SfM on evenly spaced frames with the person masked out (see module docstring)."""
    import pycolmap  # noqa: PLC0415 - the optional video extra

    cfg = config or SfmConfig()
    num, height, width = frames.shape[:3]
    intrinsic = prior_intrinsic(height, width, cfg.focal_factor)
    keyframes = np.unique(np.linspace(0, num - 1, min(cfg.max_frames, num)).round().astype(int))
    seconds: dict[str, float] = {}
    pycolmap.logging.minloglevel = 2  # its per-image INFO lines would bury the progress bars
    # COLMAP reports nothing per step to Python but each registered frame: one bar over the steps
    # (features, matching) and the registrations.
    bar = tqdm(total=len(keyframes) + 2, desc="cameras: features", unit="step", disable=not progress)
    with bar, tempfile.TemporaryDirectory(prefix="crisp-sfm-") as tmp:
        folder = Path(tmp)
        names = _write_inputs(folder, frames, masks, keyframes, cfg.mask_dilation_px)
        database = folder / "database.db"
        start = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_PINHOLE"
        reader.camera_params = f"{intrinsic[0, 0]},{width / 2},{height / 2}"
        reader.mask_path = str(folder / "masks")
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.use_gpu, extraction.num_threads = False, -1
        extraction.sift.max_num_features = cfg.max_features
        pycolmap.extract_features(database, folder / "images", image_names=names,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        seconds["features"] = time.perf_counter() - start
        bar.set_description("cameras: matching")
        bar.update()

        start = time.perf_counter()
        matching = pycolmap.FeatureMatchingOptions()
        matching.use_gpu, matching.num_threads = False, -1
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap, pairing.quadratic_overlap = 10, True
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.max_error = cfg.ransac_max_error
        verification.max_H_inlier_ratio = cfg.max_homography_inlier_ratio
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification, device=pycolmap.Device.cpu)
        seconds["matching"] = time.perf_counter() - start
        bar.set_description("cameras: mapping")
        bar.update()

        start = time.perf_counter()
        options = pycolmap.IncrementalPipelineOptions()
        options.random_seed = cfg.seed
        options.multiple_models = False  # one scene: frames that do not join the first model are not used
        options.max_runtime_seconds = int(cfg.max_mapping_seconds)
        options.ba_refine_focal_length = cfg.refine_focal
        options.ba_refine_principal_point = False
        options.mapper.init_min_tri_angle = cfg.init_min_tri_angle
        options.mapper.init_max_error = cfg.ransac_max_error
        options.mapper.filter_min_tri_angle = cfg.min_tri_angle
        options.triangulation.min_angle = cfg.min_tri_angle
        (folder / "sparse").mkdir()
        models = pycolmap.incremental_mapping(database, folder / "images", folder / "sparse", options=options,
                                              next_image_callback=lambda: bar.update())
        seconds["mapping"] = time.perf_counter() - start

    if not models:
        return static_camera(num, intrinsic, "COLMAP built no model: too little parallax or texture", seconds)
    model = max(models.values(), key=lambda m: m.num_reg_images())
    index = {name: i for i, name in enumerate(names)}
    registered = np.zeros(len(keyframes), bool)
    c2w = np.zeros((len(keyframes), 4, 4))
    point_ids = np.array(sorted(model.points3D), dtype=np.int64)
    row = {pid: i for i, pid in enumerate(point_ids)}
    visible = [np.zeros(0, int) for _ in keyframes]
    for image in model.images.values():
        i = index[image.name]
        registered[i] = image.has_pose
        if image.has_pose:
            c2w[i] = np.linalg.inv(np.vstack([image.cam_from_world().matrix(), [0, 0, 0, 1]]))
            visible[i] = np.array([row[p.point3D_id] for p in image.points2D if p.has_point3D()], dtype=int)
    share = registered.mean()
    if share < cfg.min_registered_share:
        return static_camera(num, intrinsic, f"COLMAP registered {registered.sum()} of {len(keyframes)} frames",
                             seconds)
    camera = next(iter(model.cameras.values()))
    f = float(camera.params[0])
    intrinsic = np.array([[f, 0.0, camera.params[1]], [0.0, f, camera.params[2]], [0.0, 0.0, 1.0]])
    points = np.array([model.points3D[p].xyz for p in point_ids]).reshape(-1, 3)
    colors = np.array([model.points3D[p].color for p in point_ids], dtype=np.uint8).reshape(-1, 3)
    return CameraSolve(intrinsic=intrinsic, cam_c2w=_interpolate(num, keyframes[registered], c2w[registered]),
                       keyframes=keyframes, registered=registered, points=points, colors=colors, visible=visible,
                       reprojection_error=float(model.compute_mean_reprojection_error()), seconds=seconds)
