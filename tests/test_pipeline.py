"""``crisp reconstruct`` end to end on small synthetic videos with known ground truth."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import crisp_gym  # noqa: F401  (registers CrispTrack-v0)
from crisp_gym import cli
from crisp_gym.clip import load_clip_dir
from crisp_gym.humanoid import build_humanoid
from crisp_gym.metrics import box_signed_distance, support_tops
from crisp_gym.motion import compute_kinematics
from crisp_gym.reconstruct import pipeline
from crisp_gym.reconstruct.metrics import heading_alignment
from crisp_gym.reconstruct.planes import PlaneFitConfig
from crisp_gym.synth.truth import load_ground_truth, write_synth_input
from crisp_gym.synth.video import SynthSpec, SynthVideoConfig, render_synth_video


@pytest.fixture(scope="module")
def stairs_input(tmp_path_factory) -> Path:
    video = render_synth_video(SynthSpec("stairs_up", seed=3), SynthVideoConfig(width=240, height=180), progress=False)
    return write_synth_input(tmp_path_factory.mktemp("synth") / "stairs", video)


def _args(source: Path, out: Path, **kwargs) -> pipeline.ReconstructArgs:
    return pipeline.ReconstructArgs(input=source / "input.npz", motion=source / "motion_camera.npz", output=out,
                                    **kwargs)


def test_reconstructed_stairs_support_the_true_treads(stairs_input, tmp_path):
    out = pipeline.run(_args(stairs_input, tmp_path / "clip"))
    clip = load_clip_dir(out)
    truth = load_ground_truth(stairs_input)
    meta = json.loads((out / "meta.json").read_text())
    assert set(meta["timings"]) >= {"read", "align", "planes", "contact"}
    assert meta["scale"] == pytest.approx(truth.scale, rel=0.03)

    # the pelvis paths agree up to the world's free heading and origin
    to_gt = heading_alignment(clip.motion.root_pos, truth.motion.root_pos)
    recon_root = clip.motion.root_pos @ to_gt[:3, :3].T + to_gt[:3, 3]
    assert np.median(np.linalg.norm(recon_root - truth.motion.root_pos, axis=1)) < 0.05

    # every true tread has a reconstructed surface near its height above its centre (at this
    # test's 240x180 within 4 cm; benchmarks/recon_quality.py measures full-size accuracy)
    true_tops = [b for b in truth.boxes if b.top_height() > 0.05 and b.name != "floor"]
    assert true_tops, "the stairs scene must have raised treads"
    centres = np.array([b.center[:2] for b in true_tops])
    back = np.linalg.inv(to_gt)  # query the reconstruction at the treads' centres, in its own frame
    query = np.c_[centres, np.zeros(len(centres))] @ back[:3, :3].T + back[:3, 3]
    tops = support_tops(query[:, :2], clip.boxes)
    error = np.nanmin(np.abs(tops - np.array([b.top_height() for b in true_tops])[:, None]), axis=1)
    assert error.max() < 0.04, error

    env = gym.make("CrispTrack-v0", clip=str(out))
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        obs, *_ = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    assert np.all(np.isfinite(obs["proprio"] if isinstance(obs, dict) else obs))
    env.close()


def test_no_person_visible_is_a_clear_error(stairs_input, tmp_path):
    with np.load(stairs_input / "input.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays["masks"] = np.zeros_like(arrays["masks"])
    np.savez(tmp_path / "input.npz", **arrays)
    args = pipeline.ReconstructArgs(input=tmp_path / "input.npz", motion=stairs_input / "motion_camera.npz",
                                    output=tmp_path / "clip")
    with pytest.raises(ValueError, match="person"):
        pipeline.run(args)
    assert not (tmp_path / "clip").exists()


def test_missing_key_is_a_clear_error(stairs_input, tmp_path):
    with np.load(stairs_input / "input.npz") as data:
        arrays = {k: data[k] for k in data.files if k != "cam_c2w"}
    np.savez(tmp_path / "input.npz", **arrays)
    with pytest.raises(ValueError, match="cam_c2w"):
        pipeline.run(pipeline.ReconstructArgs(input=tmp_path / "input.npz", output=tmp_path / "clip", metric=True))


def test_interrupted_run_leaves_no_clip(stairs_input, tmp_path, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("crisp_gym.clip.save_primitives", interrupted)
    with pytest.raises(KeyboardInterrupt):
        pipeline.run(_args(stairs_input, tmp_path / "clip"))
    assert not (tmp_path / "clip").exists()
    assert not any(p.name.startswith(".clip") for p in tmp_path.iterdir())


def test_without_motion_writes_a_metric_scene(stairs_input, tmp_path):
    with np.load(stairs_input / "input.npz") as data:
        arrays = {k: data[k] for k in data.files}
    scale = load_ground_truth(stairs_input).scale
    arrays["depths"] = arrays["depths"].astype(np.float32) * scale
    arrays["cam_c2w"] = arrays["cam_c2w"].copy()
    arrays["cam_c2w"][:, :3, 3] *= scale
    np.savez(tmp_path / "input.npz", **arrays)
    out = pipeline.run(pipeline.ReconstructArgs(input=tmp_path / "input.npz", output=tmp_path / "scene", metric=True))
    assert sorted(p.name for p in out.iterdir()) == ["meta.json", "primitives.json", "scene.xml"]
    boxes = json.loads((out / "primitives.json").read_text())
    assert boxes and all(b["source"] == "planar" for b in boxes)


def test_heading_alignment_recovers_a_yaw_and_shift():
    rng = np.random.default_rng(0)
    path = np.cumsum(rng.normal(size=(50, 3)) * [0.05, 0.05, 0.0], axis=0) + [0.0, 0.0, 0.9]
    yaw = 0.7
    truth = np.eye(4)
    truth[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    truth[:2, 3] = [1.5, -2.0]
    moved = path @ truth[:3, :3].T + truth[:3, 3]
    np.testing.assert_allclose(heading_alignment(path, moved), truth, atol=1e-9)


@pytest.mark.parametrize("argv, message", [
    (["--name", "../../escape", "--register"], "plain names"),
    (["--name", "a b"], "plain names"),
    (["-o", "/proc/crisp-clip"], "cannot write"),
])  # fmt: skip
def test_bad_names_and_outputs_fail_before_any_work(argv, message, tmp_path, monkeypatch, capsys):
    """Checked before the input is even read: the input here does not exist."""
    monkeypatch.chdir(tmp_path)
    read = []
    monkeypatch.setattr(pipeline, "read_frames", lambda *a, **k: read.append(a))
    assert cli.main(["reconstruct", str(tmp_path / "missing.npz"), *argv]) == 2
    assert message in capsys.readouterr().err and not read
    assert not (tmp_path / "clips").exists() and not (tmp_path.parent / "escape").exists()


def test_no_box_is_an_error_that_says_why(stairs_input, tmp_path, monkeypatch):
    """Two frames of the stairs video, with the single-view rule off: the floor aligns, but a
    planar group must be seen in three frames, so nothing survives; the run stops with the planar
    fit's counts instead of writing an empty scene."""
    no_single_view = pipeline.ReconstructConfig(planes=PlaneFitConfig(single_view_share=1.0))
    monkeypatch.setattr(pipeline, "ReconstructConfig", lambda: no_single_view)
    with np.load(stairs_input / "input.npz") as data:
        arrays = {k: data[k][:2] if k in ("depths", "cam_c2w", "images", "masks") else data[k] for k in data.files}
    scale = load_ground_truth(stairs_input).scale
    arrays["depths"] = arrays["depths"].astype(np.float32) * scale
    arrays["cam_c2w"] = arrays["cam_c2w"].copy()
    arrays["cam_c2w"][:, :3, 3] *= scale
    np.savez(tmp_path / "input.npz", **arrays)
    with pytest.raises(ValueError, match="no box survived: .* none seen in at least 3 of the 2 frames"):
        pipeline.run(pipeline.ReconstructArgs(input=tmp_path / "input.npz", output=tmp_path / "scene", metric=True))
    assert not (tmp_path / "scene").exists()


def test_keep_input_frame_writes_the_clip_in_the_inputs_own_map_frame(stairs_input, tmp_path):
    """Metric poses in a z-up map frame (the true world turned 30° and moved, its floor 0.3 m up):
    with --keep-input-frame the treads come out where the map has them, not in a world the
    pipeline re-framed; a tilted input frame is refused."""
    truth = load_ground_truth(stairs_input)
    yaw = np.radians(30.0)
    map_from_world = np.eye(4)
    map_from_world[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]]
    map_from_world[:3, 3] = [5.0, -2.0, 0.3]
    with np.load(stairs_input / "input.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays["depths"] = arrays["depths"].astype(np.float32) * truth.scale
    metric_poses = arrays["cam_c2w"].copy()
    metric_poses[:, :3, 3] *= truth.scale
    arrays["cam_c2w"] = map_from_world @ truth.world_from_input @ metric_poses
    np.savez(tmp_path / "input.npz", **arrays)
    args = pipeline.ReconstructArgs(input=tmp_path / "input.npz", motion=stairs_input / "motion_camera.npz",
                                    output=tmp_path / "clip", metric=True, keep_input_frame=True)
    clip = load_clip_dir(pipeline.run(args))
    assert json.loads((tmp_path / "clip" / "meta.json").read_text())["frame"] == "input"
    treads = [b.transformed(map_from_world) for b in truth.boxes if b.name != "floor" and b.top_height() > 0.05]
    tops = np.array([b.center + b.half_size[2] * b.rotation[:, 2] for b in treads])  # centres of the true tops
    assert np.abs(box_signed_distance(tops, clip.boxes)).max() < 0.04
    pelvis = compute_kinematics(truth.motion, build_humanoid()).body_pos[:, 0] @ map_from_world[:3, :3].T \
        + map_from_world[:3, 3]
    assert np.median(np.linalg.norm(clip.motion.root_pos - pelvis, axis=1)) < 0.05

    tilted = np.eye(4)
    tilted[:3, :3] = [[1.0, 0.0, 0.0], [0.0, np.cos(0.3), -np.sin(0.3)], [0.0, np.sin(0.3), np.cos(0.3)]]
    arrays["cam_c2w"] = tilted @ arrays["cam_c2w"]
    np.savez(tmp_path / "tilted.npz", **arrays)
    with pytest.raises(ValueError, match=r"the floor's normal is 17.\d° from \+z"):
        pipeline.run(replace(args, input=tmp_path / "tilted.npz", output=tmp_path / "tilted"))
