"""Alignment on synthetic videos with known scale, gravity and floor: through the written files,
for camera-frame and first-camera-frame motions, without a motion, and on bad input."""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from crisp_gym.humanoid import build_humanoid
from crisp_gym.motion import compute_kinematics
from crisp_gym.reconstruct.align import AlignConfig, align, depth_drift, remove_person, transform_motion
from crisp_gym.reconstruct.io import MotionInput, read_frames, read_motion
from crisp_gym.synth.depth_noise import DepthNoise
from crisp_gym.synth.truth import alignment_errors, load_ground_truth, write_synth_input
from crisp_gym.synth.video import SynthSpec, SynthVideoConfig, render_synth_video  # fmt: skip

CONFIG = SynthVideoConfig(width=128, height=96)  # whole clips: the depth errors drift over seconds


@cache
def _video(spec: SynthSpec, noise: DepthNoise | None = None):
    return render_synth_video(spec, replace(CONFIG, noise=noise or DepthNoise()), progress=False)


def _assert_accurate(errors: dict[str, float]) -> None:
    assert abs(errors["scale_error"]) < 0.02, errors
    assert errors["gravity_error_deg"] < 2.0, errors
    assert errors["floor_error_m"] < 0.02, errors


@pytest.mark.parametrize("spec, scales", [(SynthSpec("stairs_up", 11, distractors=2), (0.5, 0.7)),
                                          (SynthSpec("platform_step", 12), (1.5, 2.0)),
                                          (SynthSpec("chair_sit", 13, distractors=1), (1.5, 2.0))])
def test_noisy_input_aligns_to_the_true_scale_gravity_and_floor(tmp_path, spec, scales):
    video = _video(spec, replace(DepthNoise(), scale_range=scales))  # the input is well off scale
    out = write_synth_input(tmp_path / "in", video)
    frames = read_frames(out)
    result = align(frames, read_motion(out / "motion_camera.npz"))
    truth = load_ground_truth(out)
    _assert_accurate(alignment_errors(result.alignment.scale, result.alignment.world_from_input, truth))
    # The aligned person moves as the true one does, up to the floor-plane placement (a rotation
    # about z, a shift along the floor). The person is placed relative to the cameras, whose
    # heights carry the scale's error: heights agree within 2 % of the camera height + 2 cm.
    model = build_humanoid()
    ours = compute_kinematics(result.motion, model).body_pos
    true = compute_kinematics(truth.motion, model).body_pos
    tolerance = 0.02 * truth.cam_c2w[:, 2, 3].max() + 0.02
    assert abs(result.alignment.diagnostics["feet_height_m"]) < tolerance
    np.testing.assert_allclose(ours[..., 2], true[..., 2], atol=tolerance)
    np.testing.assert_allclose(np.linalg.norm(ours[-1] - ours[0], axis=-1), np.linalg.norm(true[-1] - true[0], axis=-1),
                               atol=0.02 * np.linalg.norm(true[-1] - true[0], axis=-1).max() + 0.02)
    # the aligned frames are the input scaled (per frame, by the drift the person measured) and
    # moved as the record says, the person removed
    kept = result.frames.valid
    assert not kept[frames.person_mask].any() and kept.sum() > 0.8 * frames.valid.sum()
    drift = depth_drift(result.alignment.diagnostics["scale_per_frame"], result.alignment.scale,
                        frames.num_frames, frames.fps)
    expected = frames.depth * (result.alignment.scale * drift)[:, None, None]
    np.testing.assert_allclose(result.frames.depth[kept], expected[kept], rtol=1e-5)
    poses = frames.scaled(result.alignment.scale).cam_c2w
    np.testing.assert_allclose(result.frames.cam_c2w, result.alignment.world_from_input @ poses, atol=1e-9)
    np.testing.assert_allclose(result.alignment.world_from_camera0, result.frames.cam_c2w[0])


def test_first_camera_frame_motion_gives_the_same_alignment():
    video = _video(SynthSpec("stairs_down", 14))
    first = np.linalg.inv(video.cam_c2w[0]) @ video.cam_c2w  # camera 0 <- camera t, metres
    motion = transform_motion(video.motion_camera, first)
    result = align(video.frames, MotionInput(motion, "camera0"))
    _assert_accurate(alignment_errors(result.alignment.scale, result.alignment.world_from_input, video))
    per_frame = align(video.frames, MotionInput(video.motion_camera, "camera"))
    assert result.alignment.scale == pytest.approx(per_frame.alignment.scale, rel=2e-3)


def test_floor_cut_off_by_the_view_takes_its_height_from_the_feet():
    """The upper-body view keeps the floor near the person out of the image: only far, noisy
    floor is seen (at this size not even enough near the person to fit), so its tilt comes from
    farther away and its height from the feet."""
    video = _video(SynthSpec("platform_step", 1, "upper_body"))
    result = align(video.frames, MotionInput(video.motion_camera, "camera"))
    diagnostics = result.alignment.diagnostics
    assert diagnostics["floor_height_source"] == "feet"
    assert diagnostics["floor_frames"] < 0.75 * diagnostics["floor_frames_searched"]
    errors = alignment_errors(result.alignment.scale, result.alignment.world_from_input, video)
    assert errors["floor_error_m"] < 0.02 and abs(errors["scale_error"]) < 0.02, errors


def test_floor_seen_only_far_away_takes_its_height_from_the_feet():
    """With the "rarely seen" rule off, the same upper-body view still hands the floor's height
    to the feet: the floor it does see lies metres from the person's path."""
    video = _video(SynthSpec("platform_step", 1, "upper_body"))
    motion = MotionInput(video.motion_camera, "camera")
    far = align(video.frames, motion, AlignConfig(floor_seen_fraction=0.0))
    diagnostics = far.alignment.diagnostics
    assert diagnostics["floor_distance_m"] > AlignConfig().floor_near_distance
    assert diagnostics["floor_height_source"] == "feet"
    errors = alignment_errors(far.alignment.scale, far.alignment.world_from_input, video)
    assert errors["floor_error_m"] < 0.02, errors
    scene = align(video.frames, motion, AlignConfig(floor_seen_fraction=0.0, floor_near_distance=np.inf))
    assert scene.alignment.diagnostics["floor_height_source"] == "scene"


def test_scale_survives_frames_where_the_person_depth_is_wrong():
    video = _video(SynthSpec("platform_step", 15))
    depth = video.frames.depth.copy()
    bad = np.arange(0, video.frames.num_frames, 4)  # a quarter of the frames: depth on the person 40 % off
    depth[bad] = np.where(video.frames.person_mask[bad], depth[bad] * 1.4, depth[bad])
    frames = replace(video.frames, depth=depth)
    result = align(frames, MotionInput(video.motion_camera, "camera"))
    assert result.alignment.scale == pytest.approx(video.scale, rel=0.02)
    per_frame = result.alignment.diagnostics["scale_per_frame"]  # frame -> that frame's scale
    corrupted = set(per_frame) & set(bad.tolist())
    assert len(corrupted) >= 10 and result.alignment.diagnostics["scale_frames_rejected"] >= len(corrupted)
    assert abs(np.mean(list(per_frame.values())) / video.scale - 1) > 0.05  # a plain mean would be far off


def test_metric_input_without_motion_uses_the_cameras_up():
    video = _video(SynthSpec("stairs_up", 16, distractors=2), replace(DepthNoise(), scale_range=(1.0, 1.0)))
    result = align(video.frames, None, metric=True)
    assert result.motion is None and result.alignment.up_source == "camera+floor"
    _assert_accurate(alignment_errors(1.0, result.alignment.world_from_input, video))


def test_person_removal_clears_the_dilated_mask_only():
    video = _video(SynthSpec("chair_sit", 13, distractors=1))
    removed = remove_person(video.frames, dilation_px=3)
    mask = video.frames.person_mask
    assert not removed.valid[mask].any()
    ys, xs = np.nonzero(mask[10])
    assert not removed.valid[10, ys.min() - 3, xs[ys == ys.min()][0]]  # 3 px above the head: gone
    far = np.ones_like(mask[10])
    far[max(ys.min() - 5, 0):ys.max() + 6, max(xs.min() - 5, 0):xs.max() + 6] = False
    np.testing.assert_array_equal(removed.depth[10][far], video.frames.depth[10][far])


def test_transform_motion_moves_every_body_rigidly():
    video = _video(SynthSpec("stairs_up", 11, distractors=2))
    model = build_humanoid()
    moved = transform_motion(video.motion_camera, video.cam_c2w)
    np.testing.assert_allclose(compute_kinematics(moved, model).body_pos,
                               compute_kinematics(video.motion, model).body_pos, atol=1e-6)
    with pytest.raises(ValueError, match="transforms must be"):
        transform_motion(video.motion, np.eye(3))


def test_bad_input_gets_a_clear_error():
    video = _video(SynthSpec("stairs_up", 11, distractors=2))
    motion = MotionInput(video.motion_camera, "camera")
    with pytest.raises(ValueError, match="metric=True"):
        align(video.frames)
    with pytest.raises(ValueError, match="no person is visible"):
        align(replace(video.frames, person_mask=np.zeros_like(video.frames.person_mask)), motion)
    with pytest.raises(ValueError, match="no person masks"):
        align(replace(video.frames, person_mask=None), motion)
    with pytest.raises(ValueError, match="world frame of its own"):
        align(video.frames, MotionInput(video.motion, "world"))
    with pytest.raises(ValueError, match="must cover the same frames"):
        align(video.frames.subset(slice(0, 50)), motion)
    with pytest.raises(ValueError, match="no floor"):
        align(video.frames, motion, AlignConfig(min_floor_points=10**7))


def test_depth_drift_follows_a_smooth_per_frame_scale_and_drops_outliers():
    fps, frames = 30.0, 240
    t = np.arange(frames)
    truth = 1.0 + 0.03 * np.sin(2 * np.pi * t / (3 * fps))  # a 3 s drift of ±3 %
    votes = {int(k): 2.0 * truth[k] for k in range(0, frames, 4)}
    votes[100] = 2.0 * 1.5  # a frame where the mask caught the background
    drift = depth_drift(votes, 2.0, frames, fps, AlignConfig(drift_seconds=0.2))
    np.testing.assert_allclose(drift, truth, atol=0.008)  # smoothing flattens the peaks a little
    assert np.all(depth_drift(votes, 2.0, frames, fps, AlignConfig(drift_seconds=0.0)) == 1.0)
