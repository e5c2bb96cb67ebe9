"""Synthetic depth videos: geometry against the true boxes, the noise model's properties,
occluded-support views, the written files and the command line."""

from __future__ import annotations

import itertools
from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from crisp_gym.clip import load_clip_dir
from crisp_gym.humanoid import build_humanoid
from crisp_gym.metrics import box_signed_distance
from crisp_gym.motion import compute_kinematics
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.io import read_frames, read_motion
from crisp_gym.reconstruct.raycast import DepthRenderer, box_mesh
from crisp_gym.synth import truth, video_cli
from crisp_gym.synth.depth_noise import DepthNoise
from crisp_gym.synth.truth import load_ground_truth, write_synth_input
from crisp_gym.synth.video import (  # fmt: skip
    SynthSpec,
    SynthVideoConfig,
    benchmark_suite,
    occluded_suite,
    render_synth_video,
)

SMALL = SynthVideoConfig(width=96, height=72, frames=40)
ONLY = {name: replace(DepthNoise.clean(), **{name: value}) for name, value in
        (("pixel_noise", 0.004), ("scale_drift", 0.03), ("flying_pixels", 1.0), ("holes", 0.1))}


@cache
def _render(spec: SynthSpec, noise: DepthNoise | None = None, size=(96, 72), frames: int | None = 40):
    config = SynthVideoConfig(width=size[0], height=size[1], frames=frames, noise=noise or DepthNoise.clean())
    return render_synth_video(spec, config, progress=False)


def _metric_world_points(video, t: int) -> np.ndarray:
    """Frame t's input points carried to the true world by the documented scale and transform."""
    scaled = video.frames.scaled(video.scale)
    return scaled.transformed(video.world_from_input).world_points(t)


@pytest.mark.parametrize("spec", [SynthSpec("stairs_up", 2, distractors=2), SynthSpec("chair_sit", 5, "low")])
def test_clean_depth_lies_on_the_true_boxes_and_the_person_in_front(spec):
    video = _render(spec, replace(DepthNoise.clean(), scale_range=(0.5, 2.0)))
    assert video.scale != 1.0
    np.testing.assert_allclose(video.frames.cam_c2w[0], np.eye(4), atol=1e-12)  # the first camera's frame
    scene_only = DepthRenderer([box_mesh(b) for b in video.boxes])
    for t in (0, 20, 39):
        points = _metric_world_points(video, t)
        valid, person = video.frames.valid[t], video.frames.person_mask[t]
        assert person.any() and (valid & ~person).sum() > 1000
        # off the person, every point is on a box's surface (the scale and transform are right)
        assert np.abs(box_signed_distance(points[valid & ~person], video.boxes)).max() < 2e-4
        # on the person, the depth is in front of the scene behind them (where a perched thigh
        # rests on the seat's edge, by only 0.07 mm)
        behind, _ = scene_only.render(video.frames.intrinsic, video.cam_c2w[t], 96, 72)
        depth = video.frames.depth[t] * video.scale
        assert np.all((depth[person] < behind[person]) | (behind[person] == 0))


def test_renders_are_reproducible_and_seeded():
    a = _render(SynthSpec("random", 3))
    b = render_synth_video(SynthSpec("random", 3), replace(SMALL, noise=DepthNoise.clean()), progress=False)
    np.testing.assert_array_equal(a.frames.depth, b.frames.depth)
    np.testing.assert_array_equal(a.frames.rgb, b.frames.rgb)
    c = _render(SynthSpec("random", 4))
    assert a.frames.depth.shape != c.frames.depth.shape or not np.array_equal(a.frames.depth, c.frames.depth)
    assert {b.name for b in a.boxes} >= {"floor", "wall"}  # random scenes carry background boxes


def test_background_boxes_keep_clear_of_the_person():
    video = _render(SynthSpec("platform_step", 1, distractors=3))
    extra = [b for b in video.boxes if b.name == "wall" or b.name.startswith("block_")]
    assert len(extra) >= 2
    joints = compute_kinematics(video.motion, build_humanoid()).body_pos.reshape(-1, 3)
    assert box_signed_distance(joints, extra).min() > 0.3


def test_pixel_noise_grows_with_depth_squared():
    spec = SynthSpec("stairs_down", 1)
    clean, noisy = _render(spec), _render(spec, ONLY["pixel_noise"])
    valid = clean.frames.valid
    d, e = clean.frames.depth[valid], (noisy.frames.depth - clean.frames.depth)[valid]
    edges = np.quantile(d, [0.0, 0.33, 0.67, 0.99])
    assert edges[2] > 1.5 * edges[1]  # the bins span a real range of depths
    for lo, hi in itertools.pairwise(edges):  # e / d² has σ = pixel_noise at every depth
        band = (d >= lo) & (d < hi)
        assert (e[band] / d[band] ** 2).std() == pytest.approx(0.004, rel=0.1)


def test_scale_drift_is_smooth_zero_mean_and_of_the_configured_size():
    spec = SynthSpec("flat_walk", 2)
    clean = _render(spec, frames=150)
    drifted = _render(spec, ONLY["scale_drift"], frames=150)
    valid = clean.frames.valid
    ratio = np.array([np.median(drifted.frames.depth[t][valid[t]] / clean.frames.depth[t][valid[t]])
                      for t in range(150)])
    assert abs(ratio.mean() - 1.0) < 1e-4  # the clip's scale is the true one
    assert ratio.std() == pytest.approx(0.03, rel=0.02)
    assert np.corrcoef(ratio[:-1], ratio[1:])[0, 1] > 0.9  # smooth, not per-frame jitter


def test_flying_pixels_sit_between_foreground_and_background_at_edges_only():
    spec = SynthSpec("chair_sit", 2)
    clean, flying = _render(spec), _render(spec, ONLY["flying_pixels"])
    for t in (5, 30):
        d, f = clean.frames.depth[t], flying.frames.depth[t]
        changed = np.abs(f - d) > 1e-5
        assert changed.sum() > 20
        pad = np.pad(d, 1, mode="edge")
        neighbours = np.stack([pad[1 + dy:1 + dy + d.shape[0], 1 + dx:1 + dx + d.shape[1]]
                               for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
        lo, hi = np.where(neighbours > 0, neighbours, np.inf).min(axis=0), neighbours.max(axis=0)
        assert np.all(hi[changed] - lo[changed] > 0.05 * lo[changed])  # a depth edge
        assert np.all((f[changed] >= lo[changed] - 1e-5) & (f[changed] <= hi[changed] + 1e-5))


def test_holes_remove_the_configured_fraction():
    spec = SynthSpec("stairs_up", 1)
    clean, holes = _render(spec), _render(spec, ONLY["holes"])
    lost = (clean.frames.valid & ~holes.frames.valid).sum() / clean.frames.valid.sum()
    assert lost == pytest.approx(0.1, abs=0.03)


@pytest.mark.parametrize("spec, hidden", [(SynthSpec("chair_sit", 3, "low"), "seat"),
                                          (SynthSpec("platform_step", 2, "upper_body"), "platform")])
def test_occluded_support_tops_are_never_seen(spec, hidden):
    video = _render(spec, size=(96, 72), frames=None)
    boxes = {b["name"]: b for b in video.meta["boxes"]}
    assert boxes[hidden]["top_visible_pixels"] == 0
    assert boxes["floor"]["top_visible_pixels"] > 0
    assert video.meta["person_pixels"]["frames_without_person"] == 0
    assert video.contacts["point"].shape[0] > 0
    # the same scene from the default orbit view does see that top: the count can be non-zero
    orbit = _render(replace(spec, view="orbit"), size=(96, 72), frames=None)
    assert {b["name"]: b for b in orbit.meta["boxes"]}[hidden]["top_visible_pixels"] > 0


def test_suites_mix_supports():
    suite = benchmark_suite()
    assert len(suite) >= 10 and len({s.seed for s in suite}) == len(suite)
    assert {"stairs_up", "stairs_down", "platform_step", "chair_sit"} <= {s.kind for s in suite}
    occluded = occluded_suite()
    assert len(occluded) >= 6 and {s.view for s in occluded} == {"low", "upper_body"}


def test_written_input_reads_back_and_its_ground_truth_is_consistent(tmp_path):
    video = _render(SynthSpec("chair_sit", 1), DepthNoise(), frames=None)  # the whole clip: stand, sit, walk
    out = write_synth_input(tmp_path / "synth", video)
    frames = read_frames(out)
    np.testing.assert_allclose(frames.depth, video.frames.depth, rtol=1e-3)  # stored as float16
    np.testing.assert_array_equal(frames.person_mask, video.frames.person_mask)
    np.testing.assert_allclose(frames.cam_c2w, video.frames.cam_c2w)
    truth = load_ground_truth(out)
    assert truth.scale == video.scale and load_clip_dir(out / "gt").motion.num_frames == frames.num_frames
    # the camera-frame motion, carried to the world by the true cameras, is the true motion
    camera = read_motion(out / "motion_camera.npz")
    model = build_humanoid()
    body = compute_kinematics(camera.motion, model).body_pos
    world = np.einsum("tij,tbj->tbi", truth.cam_c2w[:, :3, :3], body) + truth.cam_c2w[:, None, :3, 3]
    np.testing.assert_allclose(world, compute_kinematics(truth.motion, model).body_pos, atol=1e-6)
    # ground-truth contact points lie on the true support surfaces
    assert set(truth.contacts["body"]) >= {"L_Ankle", "Pelvis", "L_Hip"}
    assert np.abs(box_signed_distance(truth.contacts["point"], truth.boxes)).max() < 1e-6
    with pytest.raises(FileExistsError):
        write_synth_input(out, video)


def test_an_interrupted_write_leaves_nothing(tmp_path, monkeypatch):
    video = _render(SynthSpec("stairs_up", 1))

    def fail(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(truth, "save_camera_smpl", fail)
    with pytest.raises(KeyboardInterrupt):
        write_synth_input(tmp_path / "synth", video)
    assert list(tmp_path.iterdir()) == []


def test_command_line_writes_an_input(tmp_path):
    out = tmp_path / "cli"
    assert video_cli.main(["--kind", "platform_step", "--seed", "1", "--frames", "12", "--size", "64x48",
                           "-o", str(out)]) == 0
    frames = read_frames(out)
    assert frames.image_size == (48, 64) and frames.num_frames == 12
    assert isinstance(frames, Frames) and frames.person_mask.any()
    with pytest.raises(ValueError, match="WIDTHxHEIGHT"):
        video_cli.main(["--size", "64by48", "-o", str(tmp_path / "x")])


def test_bad_specs_are_rejected():
    with pytest.raises(ValueError, match="unknown kind"):
        SynthSpec("parkour", 0)
    with pytest.raises(ValueError, match="unknown view"):
        SynthSpec("stairs_up", 0, view="drone")
    with pytest.raises(ValueError, match="scale_range"):
        DepthNoise(scale_range=(2.0, 1.0))
