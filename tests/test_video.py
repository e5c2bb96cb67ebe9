"""The plain-video path: reading videos, scale and floor from known geometry, and the whole path
on a few frames of the real phone video (when ``../shared/data`` and the video extra are present),
with no network socket opened by it or its MediaPipe process."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import gymnasium as gym
import imageio.v3 as iio
import numpy as np
import pytest

import crisp_gym  # noqa: F401 - registers CrispTrack-v0
from crisp_gym import cli
from crisp_gym.geometry import look_at
from crisp_gym.reconstruct import person
from crisp_gym.reconstruct.body_scale import ground_metrology, implied_stature, stature_factor
from crisp_gym.reconstruct.io import is_plain_video, read_video
from crisp_gym.reconstruct.person import PersonTrack, landmark
from crisp_gym.reconstruct.pipeline import ReconstructArgs, run
from crisp_gym.reconstruct.sfm import CameraSolve
from crisp_gym.reconstruct.video import FEET, VideoConfig, floor_frame, metric_scale, person_in_camera
from tests.conftest import SHARED_DATA

VIDEO = SHARED_DATA / "videomimic_sitting"


def _frames(n: int = 6, h: int = 48, w: int = 64) -> np.ndarray:
    y, x = np.mgrid[:h, :w]
    return np.stack([np.dstack([(x * 4 + 9 * k) % 256, (y * 5) % 256, np.full((h, w), 40 * k % 256)])
                     for k in range(n)]).astype(np.uint8)


def test_video_file_and_image_folder_read_alike(tmp_path):
    frames = _frames()
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, frame in enumerate(frames):  # numeric order, not text order: 10 after 9
        iio.imwrite(folder / f"{k * 5}.png", frame)
    iio.imwrite(tmp_path / "clip.mp4", frames, fps=12, codec="libx264", macro_block_size=1, quality=10)

    from_folder, fps_folder = read_video(folder, fps=12, progress=False)
    from_file, fps_file = read_video(tmp_path / "clip.mp4", progress=False)
    np.testing.assert_array_equal(from_folder, frames)
    assert fps_folder == fps_file == pytest.approx(12)
    assert from_file.shape == frames.shape and np.abs(from_file.astype(int) - frames).mean() < 12
    small, _ = read_video(folder, max_side=32, fps=12, progress=False)
    assert small.shape[1:3] == (24, 32)
    assert is_plain_video(folder) and is_plain_video(tmp_path / "clip.mp4")


def test_bad_videos_are_named(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no images"):
        read_video(tmp_path / "empty", progress=False)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match="not a video file"):
        read_video(tmp_path / "notes.txt", progress=False)
    (tmp_path / "broken.mp4").write_bytes(b"\x00" * 100)
    with pytest.raises(ValueError, match="cannot read"):
        read_video(tmp_path / "broken.mp4", progress=False)
    with pytest.raises(FileNotFoundError):
        read_video(tmp_path / "missing.mp4", progress=False)
    one = tmp_path / "one"
    one.mkdir()
    iio.imwrite(one / "0.png", _frames(1)[0])
    with pytest.raises(ValueError, match="at least 2 frames"):
        read_video(one, progress=False)
    iio.imwrite(one / "1.png", _frames(1)[0])
    for rate in (1e-6, 0.0, np.nan, 1e5):  # the 1e-6 fps made a one-frame motion, then a misleading error
        with pytest.raises(ValueError, match=r"frame rate must be in \[1, 1000\] fps"):
            read_video(one, fps=rate, progress=False)
    depth = tmp_path / "rgbd"
    (depth / "depth").mkdir(parents=True)
    iio.imwrite(depth / "0.png", _frames(1)[0])
    assert not is_plain_video(depth)


def test_missing_video_extras_name_the_fix(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(person.platformdirs, "user_data_dir", lambda name: str(tmp_path))
    with pytest.raises(FileNotFoundError, match="crisp_gym.reconstruct.person --install"):
        person.track_person(_frames(2))
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, frame in enumerate(_frames(3)):
        iio.imwrite(folder / f"{k}.png", frame)
    assert cli.main(["reconstruct", str(folder), "-o", str(tmp_path / "clip")]) == 2
    assert "crisp_gym.reconstruct.person --install" in capsys.readouterr().err and not (tmp_path / "clip").exists()
    # A stature in centimetres is refused before anything runs.
    assert cli.main(["reconstruct", str(folder), "-o", str(tmp_path / "clip"), "--person-height", "175"]) == 2
    assert "person_height must be a human stature in metres" in capsys.readouterr().err


def _pinhole(f: float = 600.0, w: int = 640, h: int = 480) -> np.ndarray:
    return np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])


def _standing_person(frames: int, pelvis_xy: np.ndarray) -> np.ndarray:
    """(T, 33, 3) landmarks of an upright person, world z up, feet at z = 0."""
    points = np.zeros((frames, 33, 3))
    points[:, :, :2] = np.reshape(pelvis_xy, (-1, 1, 2))
    points[:, :, 2] = 1.0  # everything at chest-ish height over the pelvis unless set below
    for side, dy in (("left", 0.1), ("right", -0.1)):
        for name, z in (("hip", 0.9), ("knee", 0.5), ("ankle", 0.08), ("heel", 0.0), ("foot_index", 0.0),
                        ("shoulder", 1.4)):
            points[:, landmark(f"{side}_{name}"), :2] = pelvis_xy + [0.0, dy]
            points[:, landmark(f"{side}_{name}"), 2] = z
        points[:, landmark(f"{side}_foot_index"), 0] += 0.15
    return points


def test_scale_and_floor_from_known_geometry():
    """A floor grid seen by a moving camera, in SfM units 1/s of the metric ones, and a person
    standing on it: the scale comes back as s, the floor as z = 0 with gravity up."""
    rng = np.random.default_rng(0)
    s_true, frames = 0.0123, 8
    ground = np.c_[rng.uniform(-3, 3, (3000, 2)) + [3.0, 0.0], np.zeros(3000)]
    person_xy = np.array([3.0, 0.0])
    world = _standing_person(frames, person_xy)
    c2w = np.stack([look_at(np.array([0.0, 0.1 * k, 1.5]), np.array([3.0, 0.0, 0.5])) for k in range(frames)])
    intrinsic = _pinhole()
    in_camera = np.einsum("tba,tjb->tja", c2w[:, :3, :3], world - c2w[:, None, :3, 3])
    pixels = in_camera @ intrinsic.T
    track = PersonTrack(image=pixels[..., :2] / pixels[..., 2:], world=world - world[:, :1],
                        visibility=np.ones((frames, 33)),
                        masks=np.zeros((frames, 480, 640), bool))
    sfm_c2w = c2w.copy()
    sfm_c2w[:, :3, 3] /= s_true
    cameras = CameraSolve(intrinsic=intrinsic, cam_c2w=sfm_c2w, keyframes=np.arange(frames),
                          registered=np.ones(frames, bool), points=ground / s_true,
                          colors=np.zeros((3000, 3), np.uint8), visible=[np.arange(3000)] * frames,
                          reprojection_error=0.3)
    scale, ratios = metric_scale(track, in_camera, cameras, window_px=40)
    assert scale == pytest.approx(s_true, rel=0.02) and len(ratios) == frames

    # The same scene turned and shifted: the floor frame undoes it.
    turn = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    turn *= np.sign(np.linalg.det(turn))
    moved = lambda p: p @ turn.T + [1.0, 2.0, 3.0]  # noqa: E731
    transform, figures = floor_frame(moved(world), moved(ground), turn @ [1.0, 0, 0], VideoConfig(),
                                     np.random.default_rng(0))
    back = moved(ground) @ transform[:3, :3].T + transform[:3, 3]
    assert np.abs(back[:, 2]).max() < 1e-6
    feet = moved(world)[:, [landmark(n) for n in FEET]] @ transform[:3, :3].T + transform[:3, 3]
    assert feet[..., 2].min() == pytest.approx(0.0, abs=1e-6)
    assert figures["floor_source"] == "scene points" and figures["trunk_to_floor_deg"] < 1.0


def _seen_person(c2w: np.ndarray, world: np.ndarray, intrinsic: np.ndarray) -> PersonTrack:
    """The landmarks ``world`` (T, 33, 3) as a camera at ``c2w`` (T, 4, 4) sees them, all visible."""
    in_camera = np.einsum("tba,tjb->tja", c2w[:, :3, :3], world - c2w[:, None, :3, 3])
    pixels = in_camera @ intrinsic.T
    hips = world[:, [landmark("left_hip"), landmark("right_hip")]].mean(axis=1, keepdims=True)
    return PersonTrack(image=pixels[..., :2] / pixels[..., 2:], world=world - hips,
                       visibility=np.ones(world.shape[:2]), masks=np.zeros((len(world), 2, 2), bool))


def test_ground_metrology_measures_the_scene_against_the_body():
    """A walking person seen from a handheld camera 1.5 m up: metrology against the floor finds the
    scene the size the body says (ratio 1), and 1.25 when the scene is made 1.25 times too large
    (as a focal length 25 % too long makes PnP's depth, and the scale taken from it)."""
    frames = 12
    person_xy = np.c_[np.linspace(2.5, 3.5, frames), np.linspace(-0.3, 0.3, frames)]
    world = _standing_person(frames, person_xy)
    world[1::2, landmark("left_heel"), 2] += 0.1  # a swinging foot: the lowest one is on the floor
    c2w = np.stack([look_at(np.array([0.0, 0.02 * k, 1.5]), np.array([3.0, 0.0, 0.6])) for k in range(frames)])
    intrinsic = _pinhole()
    track = _seen_person(c2w, world, intrinsic)
    right = ground_metrology(track.image, world, np.array([landmark(n) for n in FEET]), c2w, intrinsic)
    assert len(right) == frames and np.median(right) == pytest.approx(1.0, abs=0.01)
    too_large = c2w.copy()
    too_large[:, :3, 3] *= 1.25  # the scene about the floor's origin, not the body
    ratios = ground_metrology(track.image, world, np.array([landmark(n) for n in FEET]), too_large, intrinsic)
    assert np.median(ratios) == pytest.approx(1.25, abs=0.02)


def test_a_focal_length_bundle_adjustment_got_wrong_leaves_the_scale():
    """A camera solve whose focal length is 25 or 40 % too long, its depths stretched along the
    first camera's view to match (the pixels are the same: what a small-baseline bundle
    adjustment can settle on). PnP puts the person farther by as much, but the floor is farther
    too: the scale is within 3 %, the camera's height within 2 cm, the metrology ratio 1."""
    rng = np.random.default_rng(0)
    s_true, frames = 0.01, 12
    world = _standing_person(frames, np.c_[np.linspace(2.5, 3.5, frames), np.linspace(-0.3, 0.3, frames)])
    first = look_at(np.array([0.0, 0.0, 1.5]), np.array([3.0, 0.0, 0.6]))
    c2w = np.tile(first, (frames, 1, 1))
    c2w[:, :3, 3] += np.arange(frames)[:, None] * 0.01 * first[:3, 0]  # sideways: pixels survive the stretch
    track = _seen_person(c2w, world, _pinhole())
    ground = np.c_[rng.uniform(-3, 3, (3000, 2)) + [3.0, 0.0], np.zeros(3000)]
    in_first = ground @ first[:3, :3] - first[:3, 3] @ first[:3, :3]
    sfm_c2w = c2w.copy()
    sfm_c2w[:, :3, 3] /= s_true
    for stretch in (1.0, 1.25, 1.4):
        points = (in_first * [1.0, 1.0, stretch]) @ first[:3, :3].T + first[:3, 3]
        cameras = CameraSolve(intrinsic=_pinhole(600.0 * stretch), cam_c2w=sfm_c2w, keyframes=np.arange(frames),
                              registered=np.ones(frames, bool), points=points / s_true,
                              colors=np.zeros((3000, 3), np.uint8), visible=[np.arange(3000)] * frames,
                              reprojection_error=0.3)
        in_camera = person_in_camera(track, cameras.intrinsic)
        depth = np.median(in_camera[:, landmark("left_hip"), 2] / np.linalg.norm(world[:, 0, :2], axis=1))
        assert depth == pytest.approx(stretch, rel=0.05)  # PnP: the person farther
        scale, _ = metric_scale(track, in_camera, cameras, window_px=40)
        assert scale == pytest.approx(s_true, rel=0.03)
        metric = sfm_c2w.copy()
        metric[:, :3, 3] *= scale
        in_sfm = np.einsum("tab,tjb->tja", metric[:, :3, :3], in_camera) + metric[:, None, :3, 3]
        to_floor, figures = floor_frame(in_sfm, points / s_true * scale, metric[0, :3, 2], VideoConfig(), rng)
        assert figures["floor_source"] == "scene points"
        assert (to_floor @ metric[0])[2, 3] == pytest.approx(1.5, abs=0.02)
        ratios = ground_metrology(track.image, in_sfm @ to_floor[:3, :3].T + to_floor[:3, 3],
                                  np.array([landmark(n) for n in FEET]), to_floor @ metric, cameras.intrinsic)
        assert np.median(ratios) == pytest.approx(1.0, abs=0.01)


def test_a_known_stature_sets_the_body_size():
    """Landmarks with the legs of a 1.50 m person in the anthropometric table: that is the implied
    stature, and a person known to be 1.80 m is 1.2 times their size."""
    from crisp_gym.humanoid import BODY_NAMES, default_rest_joints

    rest = default_rest_joints(1.5)
    world = np.zeros((5, 33, 3))
    for side, body in (("left", "L"), ("right", "R")):
        for joint, name in (("hip", "Hip"), ("knee", "Knee"), ("ankle", "Ankle")):
            world[:, landmark(f"{side}_{joint}")] = rest[BODY_NAMES.index(f"{body}_{name}")]
    track = PersonTrack(image=np.zeros((5, 33, 2)), world=world, visibility=np.ones((5, 33)),
                        masks=np.zeros((5, 2, 2), bool))
    assert implied_stature(track) == pytest.approx(1.5)
    assert stature_factor(track, 1.8) == pytest.approx(1.2)
    hidden = replace(track, visibility=np.zeros((5, 33)))
    with pytest.raises(ValueError, match="legs are seen in too few frames"):
        stature_factor(hidden, 1.8)
    with pytest.raises(ValueError, match="person_height must be a human stature"):
        VideoConfig(person_height=17.0)


def test_cache_keeps_the_slow_stages(tmp_path):
    """The person track and a camera solve come back from the cache as they went in; they are
    computed once per frames and settings, and other frames or settings miss."""
    from crisp_gym.reconstruct.sfm import static_camera
    from crisp_gym.reconstruct.video_cache import cached_cameras, cached_track, frames_digest

    rng = np.random.default_rng(0)
    track = PersonTrack(image=rng.normal(size=(3, 33, 2)), world=rng.normal(size=(3, 33, 3)),
                        visibility=rng.uniform(size=(3, 33)), masks=rng.uniform(size=(3, 5, 13)) > 0.5)
    cameras = CameraSolve(intrinsic=_pinhole(), cam_c2w=np.tile(np.eye(4), (3, 1, 1)), keyframes=np.array([0, 2]),
                          registered=np.array([True, False]), points=rng.normal(size=(4, 3)),
                          colors=np.zeros((4, 3), np.uint8), visible=[np.array([0, 3]), np.zeros(0, int)],
                          reprojection_error=0.25, seconds={"features": 1.5})
    calls = []
    digest = frames_digest(_frames(3))
    for _ in range(2):
        got, _ = cached_track(tmp_path, digest, lambda: calls.append("person") or track)
        solved, hit = cached_cameras(tmp_path, digest, "settings", lambda: calls.append("cameras") or cameras)
    assert calls == ["person", "cameras"] and hit
    for name in ("image", "world", "visibility", "masks"):
        np.testing.assert_array_equal(getattr(got, name), getattr(track, name))
    np.testing.assert_array_equal(solved.points, cameras.points)
    assert [v.tolist() for v in solved.visible] == [[0, 3], []] and solved.seconds == {"features": 1.5}
    assert not solved.static and solved.reprojection_error == 0.25
    cached_cameras(tmp_path, digest, "other settings", lambda: calls.append("cameras") or cameras)
    cached_track(tmp_path, frames_digest(_frames(4)), lambda: calls.append("person") or track)
    assert calls == ["person", "cameras", "cameras", "person"]
    fixed, _ = cached_cameras(tmp_path, "x", "y", lambda: static_camera(3, _pinhole(), "no parallax"))
    again, hit = cached_cameras(tmp_path, "x", "y", lambda: None)
    assert hit and again.static and again.reason == "no parallax" and again.visible == [] and len(again.points) == 0


def _runtime_ready() -> bool:
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        return False
    return person.runtime_installed()


@pytest.mark.skipif(not VIDEO.is_dir() or not _runtime_ready(),
                    reason="needs ../shared/data/videomimic_sitting, pycolmap and the MediaPipe runtime")
def test_real_video_frames_become_a_clip_without_network(tmp_path, monkeypatch):
    """Every 6th frame of the real phone video (the walk in, the sit, the stand up): a clip the
    env loads, quality flags in meta.json, a comparison video; no socket is opened, here or in the
    MediaPipe process (an audit hook in both refuses any)."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for k, image in enumerate(sorted(VIDEO.glob("*.jpg"))[::6]):
        (frames / f"{k:03d}.jpg").symlink_to(image)
    guard = tmp_path / "guard"
    guard.mkdir()
    (guard / "sitecustomize.py").write_text(
        "import sys\n"
        "def _refuse(event, args):\n"
        "    if event.startswith('socket.') and event not in ('socket.__new__',) or event == 'urllib.Request':\n"
        "        raise RuntimeError('network use in the video path: ' + event)\n"
        "sys.addaudithook(_refuse)\n")
    monkeypatch.setenv("PYTHONPATH", str(guard))
    probe = subprocess.run([sys.executable, "-c", "import socket; socket.create_connection(('127.0.0.1', 9), 1)"],
                           capture_output=True, text=True)
    assert "network use in the video path" in probe.stderr  # the guard is live in child processes
    opened = []
    refusing = [True]

    def refuse(event, args):
        if refusing[0] and event in ("socket.connect", "socket.bind", "socket.getaddrinfo", "urllib.Request"):
            opened.append(event)
            raise RuntimeError(f"network use in the video path: {event}")

    sys.addaudithook(refuse)
    try:
        out = run(ReconstructArgs(input=frames, output=tmp_path / "clip", fps=2.5, max_side=480,
                                  cache=tmp_path / "cache"))
    finally:
        refusing[0] = False
    assert not opened
    meta = json.loads((out / "meta.json").read_text())
    flags = meta["quality"]
    assert flags["cached"] == [] and len(list((tmp_path / "cache").glob("*.npz"))) == 2
    assert flags["person_found"] > 0.9 and flags["frames"] == len(list(frames.iterdir()))
    assert isinstance(flags["static_camera"], bool) and "warnings" in flags
    if flags["static_camera"]:
        assert flags["static_reason"]
    assert (out / "comparison.mp4").stat().st_size > 0
    env = gym.make("CrispTrack-v0", clip=str(out))
    obs, _ = env.reset(seed=0)
    assert np.all(np.isfinite(obs["proprio"]))
    env.close()

    # Again with a stature: MediaPipe and COLMAP are not run, and the scene grows with the person.
    again = run(ReconstructArgs(input=frames, output=tmp_path / "taller", fps=2.5, max_side=480,
                                cache=tmp_path / "cache", person_height=1.1 * flags["implied_stature_m"]))
    taller = json.loads((again / "meta.json").read_text())["quality"]
    assert taller["cached"] == ["person", "cameras"] and taller["person_height_m"] is not None
    if not flags["static_camera"]:
        assert taller["scale"] == pytest.approx(1.1 * flags["scale"], rel=0.02)


def test_a_floor_leaning_against_the_trunk_is_warned_about():
    from crisp_gym.reconstruct.sfm import static_camera
    from crisp_gym.reconstruct.video import floor_warning

    cameras = CameraSolve(intrinsic=_pinhole(), cam_c2w=np.tile(np.eye(4), (3, 1, 1)), keyframes=np.arange(64),
                          registered=np.arange(64) < 39, points=np.zeros((0, 3)), colors=np.zeros((0, 3), np.uint8),
                          visible=[], reprojection_error=0.2)
    assert floor_warning({"trunk_to_floor_deg": 4.0, "floor_source": "scene points"}, cameras, 12.0) is None
    message = floor_warning({"trunk_to_floor_deg": 20.0, "floor_source": "feet"}, cameras, 12.0)
    assert "leans 20°" in message and "39 of 64 frames registered" in message
    fixed = static_camera(3, _pinhole(), "tripod")
    assert "a fixed camera" in floor_warning({"trunk_to_floor_deg": 15.0, "floor_source": "feet"}, fixed, 12.0)


def test_upright_makes_the_standing_trunk_vertical():
    """A person whose every frame leans 8° (a monocular pose's bias) is turned upright about the
    hips; the angle is reported and a crouched frame keeps its lean relative to the standing ones."""
    from scipy.spatial.transform import Rotation

    from crisp_gym.reconstruct.video import upright

    points = _standing_person(10, np.array([1.0, 2.0]))
    points[7:, :, 2] *= 0.6  # crouched: hips lower than 0.85 of the highest
    hips = 0.5 * (points[:, landmark("left_hip")] + points[:, landmark("right_hip")])
    tilt = Rotation.from_rotvec([np.deg2rad(8.0), 0.0, 0.0]).as_matrix()
    leaning = (points - hips[:, None]) @ tilt.T + hips[:, None]
    fixed, angle = upright(leaning, hip_share=0.85)
    assert angle == pytest.approx(8.0, abs=1e-6)
    np.testing.assert_allclose(fixed, points, atol=1e-9)


@pytest.mark.parametrize("top, near, passed", [(0.25, True, True), (0.70, True, False), (0.25, False, False)])
def test_a_level_top_the_shins_cross_is_walked_through(top, near, passed):
    """A slab a few centimetres thick that the walk's shins cross holds no joint or sole point, yet
    the person walked through it (a slice of a slope or a bush); a table top above the knees, or a
    slab away from the walk, is a surface."""
    from crisp_gym.humanoid import build_humanoid
    from crisp_gym.metrics import sole_points
    from crisp_gym.motion import compute_kinematics
    from crisp_gym.reconstruct.video import _passed_through
    from crisp_gym.registry import load_clip
    from crisp_gym.scene import Box

    model = build_humanoid()
    motion = load_clip("flat_walk").motion
    body_pos = compute_kinematics(motion, model).body_pos
    soles = sole_points(model, motion.qpos())
    middle = body_pos[motion.num_frames // 2, 0, :2] + (0.0 if near else 3.0)
    slab = Box(center=[*middle, top - 0.02], half_size=[0.4, 0.4, 0.02])
    local = np.abs(np.concatenate([body_pos, soles], axis=1) - slab.center)
    assert not np.any(np.all(local <= slab.half_size - 0.02, axis=-1))  # no point lands in the slab itself
    assert _passed_through(slab, body_pos, soles) is passed
