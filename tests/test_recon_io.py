"""Reconstruction inputs: MegaSAM npz, TUM and Redwood RGB-D folders (with odometry), motions."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from crisp_gym.geometry import look_at
from crisp_gym.humanoid import build_humanoid
from crisp_gym.motion import compute_kinematics
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.io import (
    PRIMESENSE_INTRINSIC,
    SMPL_PELVIS_OFFSET,
    TUM_FR1_INTRINSIC,
    RgbdFolderConfig,
    depth_agreement,
    read_frames,
    read_megasam_npz,
    read_motion,
    read_rgbd_folder,
    save_camera_smpl,
)  # fmt: skip
from crisp_gym.reconstruct.raycast import DepthRenderer, box_mesh
from crisp_gym.scene import Box, floor_box
from tests.conftest import SHARED_DATA, sway_motion

W, H = 320, 240  # Open3D's odometry runs a 3-level pyramid: at 160 px its coarsest level is too coarse
_YAW = [Rotation.from_euler("z", a, degrees=True).as_matrix() for a in (20, -35, 50, 10)]
BOXES = [floor_box(), Box(center=[2.2, 0.3, 0.3], rotation=_YAW[0], half_size=[0.3, 0.5, 0.3]),
         Box(center=[2.5, -0.7, 0.5], rotation=_YAW[1], half_size=[0.25, 0.25, 0.5]),
         Box(center=[3.4, 0.0, 1.0], half_size=[0.1, 2.5, 1.0]),
         Box(center=[2.0, -0.1, 0.15], rotation=_YAW[2], half_size=[0.15, 0.15, 0.15]),
         Box(center=[2.8, 1.0, 0.4], rotation=_YAW[3], half_size=[0.2, 0.3, 0.4])]


def _scaled_default(default: tuple[float, float, float, float]) -> np.ndarray:
    """The folder reader's documented default camera at W x H (given for 640 x 480)."""
    fx, fy, cx, cy = default
    s = W / 640.0
    return np.array([[fx * s, 0, (cx + 0.5) * s - 0.5], [0, fy * s, (cy + 0.5) * s - 0.5], [0, 0, 1.0]])


def _trajectory(n: int = 12) -> np.ndarray:
    """A slow handheld-like sweep: 2 cm and 0.6 degrees of yaw per frame, looking at the boxes."""
    poses = []
    for k in range(n):
        eye = np.array([0.2 + 0.01 * k, -0.3 + 0.02 * k, 1.3 + 0.005 * k])
        yaw = np.radians(0.6 * k)
        target = eye + [np.cos(yaw) * 2.5, np.sin(yaw) * 2.5, -1.0]
        poses.append(look_at(eye, target))
    return np.stack(poses)


def _render(poses: np.ndarray, intrinsic: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth (m) and a textured colour image of the box scene: a 3D checker of 0.2 m cells on
    palette colours, so photometric odometry has something to lock onto."""
    renderer = DepthRenderer([box_mesh(b) for b in BOXES])
    palette = np.array([[150, 150, 140], [90, 140, 200], [200, 130, 80], [120, 180, 110]], np.float64)
    depth, rgb = [], []
    for pose in poses:
        d, ids = renderer.render(intrinsic, pose, W, H)
        points = Frames(np.where(d > 0, d, 1.0)[None], intrinsic, pose[None]).world_points(0)
        cells = np.floor(points / 0.2).astype(int).sum(axis=-1) % 2
        colour = np.where(ids[..., None] >= 0, palette[ids % len(palette)] * np.where(cells, 1.0, 0.6)[..., None], 0.0)
        depth.append(d)
        rgb.append(colour.clip(0, 255).astype(np.uint8))
    return np.stack(depth), np.stack(rgb)


def _png_depth(depth: np.ndarray, units: float) -> np.ndarray:
    """16-bit depth as a sensor writes it: beyond the range it can encode means no measurement."""
    raw = np.round(depth * units)
    return np.where(raw < 65535, raw, 0).astype(np.uint16)


def _relative(poses: np.ndarray) -> np.ndarray:
    return np.einsum("ij,tjk->tik", np.linalg.inv(poses[0]), poses)


def _pose_errors(estimated: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    """Largest translation (m) and rotation (deg) error of poses relative to their first frame."""
    a, b = _relative(estimated), _relative(true)
    trans = np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1).max()
    rot = Rotation.from_matrix(np.einsum("tji,tjk->tik", a[:, :3, :3], b[:, :3, :3])).magnitude().max()
    return float(trans), float(np.degrees(rot))


def _write_tum(folder, depth, rgb, poses=None, units: float = 5000.0):
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb_lines, depth_lines = ["# colour"], ["# depth"]
    for k in range(len(depth)):
        t = 100.0 + k / 30.0
        iio.imwrite(folder / f"rgb/{t:.6f}.png", rgb[k])
        iio.imwrite(folder / f"depth/{t + 0.004:.6f}.png", _png_depth(depth[k], units))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if poses is not None:
        lines = ["# timestamp tx ty tz qx qy qz qw"]
        for k, pose in enumerate(poses):  # at the depth timestamps, so interpolation is exact
            q = Rotation.from_matrix(pose[:3, :3]).as_quat()
            lines.append(f"{100.0 + k / 30.0 + 0.004:.6f} " + " ".join(f"{x:.9f}" for x in (*pose[:3, 3], *q)))
        (folder / "groundtruth.txt").write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def tum_scene():
    poses = _trajectory()
    k = _scaled_default(TUM_FR1_INTRINSIC)
    depth, rgb = _render(poses, k)
    return poses, k, depth, rgb


# --------------------------------------------------------------------------- MegaSAM npz


def _npz_arrays(t: int = 3) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {"depths": rng.uniform(0.5, 3.0, (t, 6, 8)).astype(np.float16),
            "intrinsic": np.array([[5.0, 0, 4], [0, 5.0, 3], [0, 0, 1]]),
            "cam_c2w": np.tile(np.eye(4), (t, 1, 1)), "images": rng.integers(0, 255, (t, 6, 8, 3), dtype=np.uint8),
            "masks": (rng.random((t, 6, 8)) < 0.2).astype(np.uint8)}


def test_megasam_npz_is_read_with_its_optional_keys(tmp_path):
    arrays = _npz_arrays()
    np.savez(tmp_path / "a.npz", **arrays, fps=np.float64(24.0))
    frames = read_megasam_npz(tmp_path / "a.npz")
    np.testing.assert_array_equal(frames.depth, arrays["depths"].astype(np.float32))
    assert frames.depth.dtype == np.float32 and frames.fps == 24.0
    np.testing.assert_array_equal(frames.rgb, arrays["images"])
    np.testing.assert_array_equal(frames.person_mask, arrays["masks"] == 1)
    del arrays["images"], arrays["masks"]
    np.savez(tmp_path / "b.npz", **arrays)
    frames = read_frames(tmp_path / "b.npz")
    assert frames.fps == 30.0 and frames.rgb is None and frames.person_mask is None
    (tmp_path / "dir").mkdir()
    np.savez(tmp_path / "dir" / "input.npz", **arrays)
    assert read_frames(tmp_path / "dir").num_frames == 3


@pytest.mark.parametrize("change, message", [
    (lambda a: a.pop("cam_c2w"), r"lacks \['cam_c2w'\]"),
    (lambda a: a.update(depths=np.ones((3, 6))), r"float \(T, H, W\)"),
    (lambda a: a.update(intrinsic=np.eye(4)), r"intrinsic must be \(3, 3\)"),
    (lambda a: a.update(cam_c2w=np.tile(np.eye(4), (2, 1, 1))), r"cam_c2w must be \(3, 4, 4\)"),
    (lambda a: a["cam_c2w"].__setitem__((1, 0, 3), np.nan), "NaN or infinite values in 1 frames"),
    (lambda a: a["cam_c2w"].__setitem__((2, 2, 2), -1.0), "determinant -1: a mirror"),
    (lambda a: a["cam_c2w"].__setitem__((1, 3, 2), 5.0), r"bottom rows must be \[0, 0, 0, 1\]"),
    (lambda a: a.update(images=np.zeros((3, 6, 8, 3), np.float32)), "images must be uint8"),
    (lambda a: a.update(masks=np.zeros((3, 6, 7))), "masks must be"),
    (lambda a: a.update(depths=np.full((3, 6, 8), np.nan)), "no valid"),
])
def test_bad_megasam_npz_gets_a_clear_error(tmp_path, change, message):
    arrays = _npz_arrays()
    change(arrays)
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=message):
        read_megasam_npz(tmp_path / "bad.npz")


def test_missing_and_unreadable_inputs(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_frames(tmp_path / "nothing.npz")
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(ValueError, match="not a readable npz"):
        read_frames(tmp_path / "junk.npz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="neither a TUM folder"):
        read_frames(tmp_path / "empty")


# --------------------------------------------------------------------------- RGB-D folders


def test_tum_folder_with_groundtruth_reads_metric_depth_and_true_poses(tmp_path, tum_scene):
    poses, k, depth, rgb = tum_scene
    _write_tum(tmp_path, depth, rgb, poses)
    frames = read_rgbd_folder(tmp_path, progress=False)
    assert frames.num_frames == len(poses) and frames.fps == pytest.approx(30.0, rel=1e-3)
    np.testing.assert_allclose(frames.intrinsic, k)
    np.testing.assert_allclose(frames.depth, _png_depth(depth, 5000) / 5000, atol=1e-6)
    assert np.abs(frames.depth - depth)[frames.depth > 0].max() <= 0.5 / 5000 + 1e-6  # PNG quantisation
    np.testing.assert_allclose(frames.cam_c2w, poses, atol=1e-6)
    np.testing.assert_array_equal(frames.rgb, rgb)


def test_tum_folder_without_poses_is_tracked_by_odometry(tmp_path, tum_scene):
    """The chained frame-to-frame odometry against the true trajectory (11 steps of 2.2 cm and
    0.6 deg, 24 cm and 6.6 deg in all).

    Tolerance: started at the true motion, Open3D's dense odometry settles a few mm and about
    0.05 deg away from it on these renders (its objective's own optimum with PNG-quantised depth
    and aliased texture), and the chain adds these up over 11 pairs: 1.3 cm and 0.3 deg
    measured. 3 cm and 1 deg keep a margin of two, while every chaining mistake (identity,
    inverted or mis-composed motions) is off by at least the whole trajectory (24 cm, 6.6 deg).
    """
    poses, _, depth, rgb = tum_scene
    _write_tum(tmp_path, depth, rgb)
    frames = read_rgbd_folder(tmp_path, progress=False)
    np.testing.assert_allclose(frames.cam_c2w[0], np.eye(4))
    trans, rot = _pose_errors(frames.cam_c2w, poses)
    assert trans < 0.03 and rot < 1.0, (trans, rot)


def test_depth_agreement_tells_right_poses_from_lost_odometry(tum_scene):
    """Frame-to-frame odometry can converge to a wrong motion (on a real five-frame room folder:
    24-120° off); the depth the two frames share says so: with the true poses nearly every
    overlapping pixel agrees, with a pose 10° or 20 cm off few do."""
    poses, k, depth, _ = tum_scene
    assert depth_agreement(depth, k, poses, 5, 4) > 0.9
    turned, moved = poses.copy(), poses.copy()
    turned[5, :3, :3] = turned[5, :3, :3] @ Rotation.from_euler("y", 10, degrees=True).as_matrix()
    moved[5, :3, 3] += [0.2, 0.0, 0.0]
    assert depth_agreement(depth, k, turned, 5, 4) < 0.5 and depth_agreement(depth, k, moved, 5, 4) < 0.5


def test_redwood_folder_with_intrinsic_json_and_log(tmp_path, tum_scene):
    poses, _, _, _ = tum_scene
    k = _scaled_default(PRIMESENSE_INTRINSIC) * [[1.1, 1, 1], [1, 1.1, 1], [1, 1, 1]]  # not the default
    depth, rgb = _render(poses, k)
    (tmp_path / "color").mkdir()
    (tmp_path / "depth").mkdir()
    for i in range(len(poses)):
        iio.imwrite(tmp_path / f"color/{i:06d}.jpg", rgb[i], quality=95)
        iio.imwrite(tmp_path / f"depth/{i:06d}.png", _png_depth(depth[i], 1000))
    (tmp_path / "intrinsic.json").write_text(json.dumps(
        {"width": W, "height": H, "intrinsic_matrix": k.T.reshape(-1).tolist()}))
    frames = read_rgbd_folder(tmp_path, progress=False)  # no trajectory: odometry on JPEG colour
    np.testing.assert_allclose(frames.intrinsic, k)
    np.testing.assert_allclose(frames.depth, _png_depth(depth, 1000) / 1000, atol=1e-6)
    trans, rot = _pose_errors(frames.cam_c2w, poses)
    assert trans < 0.03 and rot < 1.0, (trans, rot)
    log = []
    for i, pose in enumerate(poses):  # the Redwood .log: "id id id" then the camera -> world matrix
        log.append(f"{i} {i} {i + 1}")
        log += [" ".join(f"{x:.10f}" for x in row) for row in pose]
    (tmp_path / "trajectory.log").write_text("\n".join(log) + "\n")
    np.testing.assert_allclose(read_rgbd_folder(tmp_path, progress=False).cam_c2w, poses, atol=1e-8)


def test_redwood_default_camera_and_pairing_errors(tmp_path, tum_scene):
    poses, _, _, _ = tum_scene
    k = _scaled_default(PRIMESENSE_INTRINSIC)
    depth, rgb = _render(poses[:3], k)
    (tmp_path / "image").mkdir()
    (tmp_path / "depth").mkdir()
    for i in range(3):
        iio.imwrite(tmp_path / f"image/{i:03d}.png", rgb[i])
        iio.imwrite(tmp_path / f"depth/{i:03d}.png", _png_depth(depth[i], 1000))
    np.testing.assert_allclose(read_rgbd_folder(tmp_path, progress=False).intrinsic, k)
    (tmp_path / "camera.txt").write_text("# fx fy cx cy depth_scale\n100 101 80 60 500\n")
    frames = read_rgbd_folder(tmp_path, progress=False)
    np.testing.assert_allclose(frames.intrinsic, [[100, 0, 80], [0, 101, 60], [0, 0, 1]])
    np.testing.assert_allclose(frames.depth, _png_depth(depth[:3], 1000) / 500, atol=1e-6)
    (tmp_path / "depth" / "000.png").unlink()
    with pytest.raises(ValueError, match="pair one to one"):
        read_rgbd_folder(tmp_path, progress=False)


# --------------------------------------------------------------------------- motions


def _camera_poses(n: int) -> np.ndarray:
    return np.stack([look_at([0.5 + 0.02 * k, -3.0, 1.5], [0.3 * k / n, 0.0, 0.9]) for k in range(n)])


def test_camera_smpl_round_trip_places_the_body_where_the_cameras_see_it(tmp_path):
    """Write a world motion as camera-frame SMPL parameters, read it back, carry it to the
    world with the camera poses: every body lands where forward kinematics of the original puts it."""
    model = build_humanoid()
    world = sway_motion(frames=20)
    poses = _camera_poses(world.num_frames)
    rot_wc = np.swapaxes(poses[:, :3, :3], 1, 2)
    root = Rotation.from_matrix(rot_wc) * Rotation.from_quat(world.root_quat, scalar_first=True)
    camera = type(world)(fps=world.fps, root_pos=np.einsum("tij,tj->ti", rot_wc, world.root_pos - poses[:, :3, 3]),
                         root_quat=root.as_quat(scalar_first=True), dof_pos=world.dof_pos)
    path = save_camera_smpl(camera, tmp_path / "incam.npz")
    with np.load(path) as data:
        assert data["body_pose"].shape == (20, 69)
        np.testing.assert_allclose(data["transl"], camera.root_pos - SMPL_PELVIS_OFFSET)
    read = read_motion(path)
    assert read.frame == "camera" and read.motion.fps == world.fps
    body_cam = compute_kinematics(read.motion, model).body_pos
    body_world = np.einsum("tij,tbj->tbi", poses[:, :3, :3], body_cam) + poses[:, None, :3, 3]
    np.testing.assert_allclose(body_world, compute_kinematics(world, model).body_pos, atol=1e-6)
    # GVHMR's own results file: a torch dict with smpl_params_incam
    with np.load(path) as data:
        torch.save({"smpl_params_incam": {k: torch.from_numpy(data[k]) for k in ("global_orient", "body_pose",
                                                                                  "transl")}},
                   tmp_path / "hmr4d_results.pt")
    from_pt = read_motion(tmp_path / "hmr4d_results.pt", fps=world.fps, frame="camera0")
    assert from_pt.frame == "camera0"
    np.testing.assert_allclose(from_pt.motion.root_pos, read.motion.root_pos, atol=1e-9)


def test_motion_npz_is_a_world_motion_and_bad_motions_are_rejected(tmp_path):
    motion = sway_motion(frames=10)
    motion.save(tmp_path / "motion.npz")
    read = read_motion(tmp_path / "motion.npz")
    assert read.frame == "world"
    np.testing.assert_allclose(read.motion.root_pos, motion.root_pos)
    np.savez(tmp_path / "partial.npz", global_orient=np.zeros((4, 3)), transl=np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"missing \['body_pose'\]"):
        read_motion(tmp_path / "partial.npz")
    np.savez(tmp_path / "wide.npz", global_orient=np.zeros((4, 3)), body_pose=np.zeros((4, 50)),
             transl=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="body_pose must have shape"):
        read_motion(tmp_path / "wide.npz")
    (tmp_path / "m.txt").write_text("")
    with pytest.raises(ValueError, match="unsupported motion file"):
        read_motion(tmp_path / "m.txt")
    with pytest.raises(FileNotFoundError):
        read_motion(tmp_path / "none.npz")


def _slambook_folder(root, names=("1", "2", "10"), depth_mm=2000):
    """A slambook2-style folder: color/N.png, 16-bit depth/N.pgm in millimetres, pose.txt lines
    'tx ty tz qx qy qz qw' (camera to world), no camera file."""
    import cv2

    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    poses = []
    for i, name in enumerate(names):
        depth = np.full((48, 64), depth_mm + 100 * i, dtype=np.uint16)  # frame i at 2.0 + 0.1 i m
        assert cv2.imwrite(str(root / "depth" / f"{name}.pgm"), depth)
        iio.imwrite(root / "color" / f"{name}.png", np.full((48, 64, 3), 30 * i, dtype=np.uint8))
        quat = Rotation.from_euler("z", 10.0 * i, degrees=True).as_quat()
        poses.append([0.1 * i, 0.0, 0.0, *quat])
    (root / "pose.txt").write_text("\n".join(" ".join(f"{v:.9f}" for v in p) for p in poses) + "\n")
    return poses


def test_slambook_folder_with_pgm_depth_pose_lines_and_given_camera(tmp_path):
    poses = _slambook_folder(tmp_path / "rgbd")
    config = RgbdFolderConfig(intrinsics=(50.0, 51.0, 31.5, 23.5), depth_scale=1000.0)
    frames = read_rgbd_folder(tmp_path / "rgbd", config, progress=False)
    np.testing.assert_allclose(frames.intrinsic, [[50, 0, 31.5], [0, 51, 23.5], [0, 0, 1]])
    # numeric order (1, 2, 10), millimetres to metres, each frame with its own pose line
    np.testing.assert_allclose(frames.depth[:, 0, 0], [2.0, 2.1, 2.2], atol=1e-6)
    for pose, c2w in zip(poses, frames.cam_c2w):
        np.testing.assert_allclose(c2w[:3, 3], pose[:3], atol=1e-9)
        np.testing.assert_allclose(Rotation.from_matrix(c2w[:3, :3]).as_quat(), pose[3:], atol=1e-8)
    with pytest.raises(ValueError, match="depth scale"):
        read_rgbd_folder(tmp_path / "rgbd", RgbdFolderConfig(depth_scale=0.0), progress=False)
    (tmp_path / "rgbd" / "pose.txt").write_text("0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="expected 3 lines"):
        read_rgbd_folder(tmp_path / "rgbd", config, progress=False)


@pytest.mark.skipif(not (SHARED_DATA / "slambook2_rgbd").is_dir(), reason="../shared/data/slambook2_rgbd is absent")
def test_real_slambook_folder_reads_as_it_is():
    """The five real Kinect frames: PGM depth in millimetres, pose.txt, camera from the options."""
    config = RgbdFolderConfig(intrinsics=(518.0, 519.0, 325.5, 253.5), depth_scale=1000.0)
    frames = read_rgbd_folder(SHARED_DATA / "slambook2_rgbd", config, progress=False)
    assert frames.num_frames == 5 and frames.depth.shape[1:] == (480, 640)
    valid = frames.depth[frames.depth > 0]
    assert 1.0 < np.median(valid) < 5.0  # a room in metres, not millimetres or 1/5000 m
    np.testing.assert_allclose(frames.cam_c2w[:, 3, :3], 0.0)
    assert np.linalg.norm(frames.cam_c2w[-1, :3, 3] - frames.cam_c2w[0, :3, 3]) > 0.3  # the camera moves


def test_a_wrong_depth_scale_is_warned_about(tmp_path, caplog):
    """Millimetre depth read with TUM's 1/5000 m makes a 2-2.2 m scene 0.4 m deep: the reader says
    so and names the scale that gives a room."""
    _slambook_folder(tmp_path / "rgbd")
    intrinsics = (50.0, 51.0, 31.5, 23.5)
    with caplog.at_level("WARNING", logger="crisp_gym.reconstruct.io"):
        frames = read_rgbd_folder(tmp_path / "rgbd", RgbdFolderConfig(intrinsics=intrinsics, depth_scale=5000.0),
                                  progress=False)
    assert frames.depth.max() < 0.5
    assert "--depth-scale 1000 (millimetres: median 2.10 m)" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="crisp_gym.reconstruct.io"):
        read_rgbd_folder(tmp_path / "rgbd", RgbdFolderConfig(intrinsics=intrinsics, depth_scale=1000.0),
                         progress=False)
    assert "depth scale" not in caplog.text
