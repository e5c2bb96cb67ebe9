"""Tests of the evaluation (``train/evaluate.py`` and its roll-outs and metrics): metrics against known answers, rollouts
against the env, the policy file and ``crisp eval``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES
from crisp_gym.train.rollouts import evaluate, record_rollout, torch_policy, zero_policy
from crisp_gym.train.tracking_metrics import accel_error, jitter, rigid_align, segment_mpjpe
from tests.test_train import SMALL_MLP, _obs, clip_dir  # noqa: F401  (clip_dir is a fixture)


def _pose(seed: int = 0, joints: int = 24) -> np.ndarray:
    return np.random.default_rng(seed).normal(scale=0.4, size=(joints, 3))


def _rigid(x: np.ndarray, seed: int) -> np.ndarray:
    rotation = Rotation.random(random_state=seed)
    return rotation.apply(x.reshape(-1, 3)).reshape(x.shape) + np.array([1.5, -2.0, 0.3])


# ----------------------------------------------------------------------------- metrics


def test_mpjpe_of_a_constant_offset() -> None:
    ref = np.stack([_pose(k) for k in range(150)])
    pred = ref + np.array([0.03, 0.04, 0.0])  # 50 mm for every joint and frame
    assert segment_mpjpe(pred, ref, "none") == pytest.approx(50.0)
    # both alignments remove a translation
    assert segment_mpjpe(pred, ref, "first_two") == pytest.approx(0.0, abs=1e-9)
    assert segment_mpjpe(pred, ref, "segment") == pytest.approx(0.0, abs=1e-9)


def test_drift_known_answers_per_alignment() -> None:
    """A static pose drifting 1 mm per frame along x, over two 100-frame segments.

    Unaligned: the mean offset, 99.5 mm. W (fit on frames 0 and 1 of each segment): the
    residual at frame k of a segment is |k - 0.5| mm, mean 49.01 mm. WA (fit on the whole
    segment): |k - 49.5| mm, mean 25 mm. The fitted rotation is the identity in both cases
    (the frames are translated copies of one pose).
    """
    frames = 200
    ref = np.broadcast_to(_pose(), (frames, 24, 3))
    pred = ref + np.arange(frames)[:, None, None] * np.array([0.001, 0.0, 0.0])
    assert segment_mpjpe(pred, ref, "none") == pytest.approx(99.5)
    assert segment_mpjpe(pred, ref, "first_two") == pytest.approx(49.01, abs=1e-6)
    assert segment_mpjpe(pred, ref, "segment") == pytest.approx(25.0, abs=1e-6)


def test_wa_mpjpe_is_invariant_to_a_rigid_transform() -> None:
    rng = np.random.default_rng(3)
    ref = np.stack([_pose(k) for k in range(250)])  # segments of 100, 100 and 50 frames
    pred = ref + rng.normal(scale=0.02, size=ref.shape)
    moved = _rigid(pred, seed=4)
    assert segment_mpjpe(moved, ref, "none") > 1000.0
    assert segment_mpjpe(moved, ref, "segment") == pytest.approx(segment_mpjpe(pred, ref, "segment"), rel=1e-9)
    # a rigidly moved copy of the reference has no error after either alignment
    assert segment_mpjpe(_rigid(ref, seed=5), ref, "segment") == pytest.approx(0.0, abs=1e-6)
    assert segment_mpjpe(_rigid(ref, seed=6), ref, "first_two") == pytest.approx(0.0, abs=1e-6)
    # the least-squares fit cannot do worse (in the squared sense) than no alignment
    aligned = rigid_align(pred, ref)
    assert np.square(aligned - ref).sum() <= np.square(pred - ref).sum()


def test_jitter_of_known_signals() -> None:
    fps = 30.0
    t = np.arange(60) / fps
    c = 0.7
    cubic = np.zeros((60, 24, 3))
    cubic[..., 0] = (c * t ** 3)[:, None]  # jerk 6c everywhere; finite differences are exact on cubics
    assert jitter(cubic, fps) == pytest.approx(6 * c, rel=1e-6)
    linear = np.zeros((60, 2, 3))
    linear[..., 2] = (1.3 * t)[:, None]
    assert jitter(linear, fps) == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="T >= 4"):
        jitter(cubic[:3], fps)


def test_accel_error_of_a_constant_acceleration() -> None:
    fps, a = 30.0, 2.0  # m/s²
    t = np.arange(40) / fps
    ref = np.broadcast_to(_pose(), (40, 24, 3))
    pred = ref + (0.5 * a * t ** 2)[:, None, None] * np.array([0.0, 1.0, 0.0])
    # second difference of a t²/2 is a/fps² metres per frame²
    assert accel_error(pred, ref) == pytest.approx(1000.0 * a / fps ** 2, rel=1e-9)
    assert accel_error(ref, ref) == 0.0


def test_metric_input_errors() -> None:
    ref = np.zeros((10, 24, 3))
    with pytest.raises(ValueError, match="same shape"):
        segment_mpjpe(ref[:5], ref)
    with pytest.raises(ValueError, match="align"):
        segment_mpjpe(ref, ref, "procrustes")
    with pytest.raises(ValueError, match=r"\(T, J, 3\)"):
        accel_error(ref[..., :2], ref[..., :2])


# ----------------------------------------------------------------------------- rollouts


def test_rollout_matches_the_batched_env(clip_dir: Path) -> None:  # noqa: F811
    """The recorded single-env rollout and the batched evaluation agree from frame 0."""
    rollout = record_rollout(zero_policy, clip_dir, 0, progress=False)
    batched = evaluate(zero_policy, clip_dir, [0, 30])
    assert rollout.steps == batched.lengths[0]
    assert rollout.rewards.sum() == pytest.approx(batched.returns[0], rel=1e-9)
    assert rollout.success == bool(batched.success[0])
    # the recorded positions are the ones the env measured its errors on
    np.testing.assert_allclose(np.linalg.norm(rollout.body_pos - rollout.ref_body_pos, axis=-1).max(-1),
                               rollout.max_body_error, atol=1e-9)
    assert rollout.max_body_error[0] == pytest.approx(0.0, abs=1e-9)  # starts on the reference
    metrics = rollout.metrics()
    assert metrics["frames_tracked"] == rollout.steps
    assert metrics["success"] == (metrics["frames_tracked"] == metrics["frames_total"])
    assert metrics["mpjpe_mm"] <= 1000.0 * rollout.max_body_error.mean() + 1e-9
    assert set(metrics["mean_reward_terms"]) == {"pos", "rot", "vel", "ang_vel", "height", "energy"}
    assert rollout.torques.shape == (rollout.steps, 69)


def test_torch_policy_runs_on_one_thread_and_returns_the_mean() -> None:
    """Between simulation steps the forward pass runs on one torch thread (its spinning workers
    would take cores from MuJoCo's); the caller's thread count is back afterwards."""
    seen = []

    class Actor(torch.nn.Module):
        def forward(self, proprio, targets):
            seen.append(torch.get_num_threads())
            return proprio[:, :3] * 2.0, torch.ones(len(proprio), 3)

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        obs = {"proprio": np.arange(8, dtype=np.float32).reshape(2, 4), "targets": np.zeros((2, 1, 5), np.float32)}
        action = torch_policy(Actor(), scene_aware=False)(obs)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert seen == [1]
    np.testing.assert_array_equal(action, [[0, 2, 4], [8, 10, 12]])


def test_rsi_start_frames_are_seeded(clip_dir: Path) -> None:  # noqa: F811
    a = evaluate(zero_policy, clip_dir, 12, seed=7)
    b = evaluate(zero_policy, clip_dir, 12, seed=7)
    np.testing.assert_array_equal(a.start_frames, b.start_frames)
    np.testing.assert_array_equal(a.returns, b.returns)
    assert len(np.unique(a.start_frames)) > 1
    # episodes end at the clip's last frame at the latest
    assert np.all(a.start_frames + a.lengths <= 89)
    assert a.fps > 0


def test_failure_clusters_group_nearby_ends() -> None:
    from crisp_gym.train.rollouts import failure_clusters

    ends = np.array([57, 58, 58, 81, 80, 120, 182, 182, 183, 182, 248, 248])
    failed = np.array([1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0], dtype=bool)
    assert failure_clusters(ends, failed) == [
        {"first_frame": 182, "last_frame": 183, "episodes": 4},
        {"first_frame": 57, "last_frame": 58, "episodes": 3},
        {"first_frame": 80, "last_frame": 81, "episodes": 2},
    ]  # the lone failure at 120 and the successes are no cluster
    assert failure_clusters(ends, np.zeros(len(ends), dtype=bool)) == []
    # a gap of exactly `gap` frames joins, one more splits
    assert failure_clusters(np.array([10, 13, 17]), np.ones(3, dtype=bool), min_episodes=1) == [
        {"first_frame": 10, "last_frame": 13, "episodes": 2}, {"first_frame": 17, "last_frame": 17, "episodes": 1}]
    # with the bodies that ended each episode: counted per cluster, most first
    hand, toe, head = BODY_NAMES.index("R_Hand"), BODY_NAMES.index("R_Toe"), BODY_NAMES.index("Head")
    bodies = np.array([hand, toe, hand, head, head, toe, toe, hand, toe, toe, hand, hand])
    clusters = failure_clusters(ends, failed, bodies)
    assert [c["bodies"] for c in clusters] == [{"R_Toe": 3, "R_Hand": 1}, {"R_Hand": 2, "R_Toe": 1}, {"Head": 2}]
    assert [{k: v for k, v in c.items() if k != "bodies"} for c in clusters] == failure_clusters(ends, failed)


def _farthest_body_at_the_end(clip: Path, start: int) -> str:
    """The PD reference's episode from ``start`` in the single env: the body farthest from its
    reference after the last step, measured here from the simulation's body positions."""
    from crisp_gym.envs.track import CrispTrackEnv

    env = CrispTrackEnv(clip=str(clip))
    env.reset(seed=0, options={"start_frame": start})
    while True:
        _, _, terminated, truncated, _ = env.step(np.zeros(69, dtype=np.float32))
        if terminated or truncated:
            break
    reference = env.task.reference.body_pos[env.task.library.global_frames(env._clip, env._frame)[0]]
    body_pos = np.array([env.data.xpos[env.model.body(name).id] for name in BODY_NAMES])
    return BODY_NAMES[int(np.argmax(np.linalg.norm(reference - body_pos, axis=-1)))]


def test_start_sweep_matches_single_starts(clip_dir: Path) -> None:  # noqa: F811
    """Each sweep episode is the episode from that start alone, and starts cover the clip."""
    from crisp_gym.train.evaluate import start_sweep

    entry, sweep = start_sweep(zero_policy, clip_dir, 20, 90)
    assert entry["start_frames"] == [0, 20, 40, 60, 80]
    for start, end, ok, body in zip(entry["start_frames"], entry["end_frames"], entry["success"], entry["end_bodies"],
                                   strict=True):
        alone = evaluate(zero_policy, clip_dir, [start])
        assert end == start + alone.lengths[0] and ok == bool(alone.success[0])
        assert start < end <= 89 and ok == (end == 89)
        assert body == _farthest_body_at_the_end(clip_dir, start)
    assert entry["success_rate"] == pytest.approx(np.mean(entry["success"]))
    with pytest.raises(ValueError, match="start-every"):
        start_sweep(zero_policy, clip_dir, 0, 90)


def test_rendered_rollout(clip_dir: Path) -> None:  # noqa: F811
    rollout = record_rollout(zero_policy, clip_dir, 80, render=True, progress=False, render_width=64,
                             render_height=48)
    assert len(rollout.images) == rollout.steps + 1
    assert rollout.images[0].shape == (48, 64, 3)


# ----------------------------------------------------------------------------- policy file and CLI


@pytest.fixture(scope="module")
def untrained_run(clip_dir: Path, tmp_path_factory) -> Path:  # noqa: F811
    from crisp_gym.train.ppo import train
    from tests.test_train import _tiny_config

    output = tmp_path_factory.mktemp("eval_run")
    train(_tiny_config(clip_dir, output, frames=512, num_envs=4, steps_per_env=64))
    return output


def test_policy_file_round_trip(untrained_run: Path, tmp_path: Path) -> None:
    from crisp_gym.policy.files import policy_training_stats, write_policy_file
    from crisp_gym.train.checkpoints import load_policy

    path = write_policy_file(untrained_run, tmp_path / "shipped", clip="walk")
    from_checkpoint, cfg = load_policy(untrained_run)
    from_file, file_cfg = load_policy(path.parent)
    assert file_cfg.clip == ("walk",) and file_cfg.model == cfg.model
    obs = _obs((6,), False, seed=1)
    torch.testing.assert_close(from_file(*obs)[0], from_checkpoint(*obs)[0], rtol=0, atol=0)
    stats = policy_training_stats(path)
    assert stats["frames"] == 512 and stats["iterations"] == 2 and stats["wall_time_s"] > 0
    assert path.stat().st_size < 0.5 * (untrained_run / "checkpoint.pt").stat().st_size
    with pytest.raises(FileNotFoundError):
        load_policy(tmp_path / "missing")
    (tmp_path / "junk.pt").write_bytes(b"")
    torch.save({"hello": 1}, tmp_path / "junk.pt")
    with pytest.raises(ValueError, match="neither"):
        load_policy(tmp_path / "junk.pt")


def test_cli_writes_report_and_plots(untrained_run: Path, clip_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    from crisp_gym.train.evaluate import main

    out = tmp_path / "eval"
    assert main([str(untrained_run), "--clip", str(clip_dir), "-o", str(out), "--episodes", "8", "--no-video"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["rsi"]["episodes"] == 8 and 0.0 <= report["rsi"]["success_rate"] <= 1.0
    full = report["from_frame_0"]
    for key in ("w_mpjpe_mm", "wa_mpjpe_mm", "mpjpe_mm", "jitter_m_s3", "accel_error_mm_frame2"):
        assert np.isfinite(full[key]) and full[key] >= 0.0, key
    assert report["training"]["frames"] == 512
    assert (out / "tracking.png").stat().st_size > 0 and (out / "torques.png").stat().st_size > 0
    assert not (out / "rollout.mp4").exists() and not (out / "starts.png").exists()
    assert not list(out.glob("*.tmp*"))
    with pytest.raises(ValueError, match="episodes"):
        main([str(untrained_run), "--clip", str(clip_dir), "-o", str(out), "--episodes", "0"])
    with pytest.raises(ValueError, match="start-every"):
        main([str(untrained_run), "--clip", str(clip_dir), "-o", str(out), "--start-every", "-1"])
    swept = tmp_path / "swept"
    assert main([str(untrained_run), "--clip", str(clip_dir), "-o", str(swept), "--episodes", "2", "--no-video",
                 "--start-every", "30"]) == 0
    sweep = json.loads((swept / "report.json").read_text())["start_sweep"]
    assert sweep["start_frames"] == [0, 30, 60] and len(sweep["end_frames"]) == 3
    assert (swept / "starts.png").stat().st_size > 0 and "starts.png" in (swept / "report.html").read_text()


def test_demo_reports_policy_and_pd_reference(untrained_run: Path, clip_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    from crisp_gym.train.demo import main

    out = tmp_path / "demo"
    assert main(["--clip", str(clip_dir), "--policy", str(untrained_run), "-o", str(out), "--episodes", "4",
                 "--no-video"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["controller"] == "policy"
    baseline = report["comparison"]["pd_reference"]
    assert baseline["controller"] == "pd_reference" and baseline["rsi"]["episodes"] == 4
    # the PD-reference row is the zero-residual rollout, recorded independently here
    expected = record_rollout(zero_policy, clip_dir, 0, progress=False).metrics()
    assert baseline["from_frame_0"]["frames_tracked"] == expected["frames_tracked"]
    assert baseline["from_frame_0"]["w_mpjpe_mm"] == pytest.approx(expected["w_mpjpe_mm"])
    # a clip without a shipped policy gets the PD-reference controller alone
    assert main(["--clip", str(clip_dir), "-o", str(out), "--episodes", "2", "--no-video"]) == 0
    assert json.loads((out / "report.json").read_text())["controller"] == "pd_reference"


def test_ship_writes_policy_log_curve_and_evaluation(untrained_run: Path, clip_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    from crisp_gym import cli
    from crisp_gym.train.ship import read_progress

    out = tmp_path / "shipped"
    argv = ["ship", str(untrained_run), "--clip", str(clip_dir), "-o", str(out), "--episodes", "4", "--smooth", "2"]
    assert cli.main(argv) == 0  # `crisp ship`, not `python -m crisp_gym.train.ship`
    report = json.loads((out / "eval.json").read_text())
    assert set(report["clips"]) == {clip_dir.name} and report["clips"][clip_dir.name]["rsi"]["episodes"] == 4
    assert {p.name for p in out.iterdir()} == {"policy.pt", "progress.csv", "learning_curve.png", "eval.json"}
    original, shipped = read_progress(untrained_run / "progress.csv"), read_progress(out / "progress.csv")
    assert list(shipped) == list(original)
    for key in original:
        np.testing.assert_allclose(shipped[key], original[key], rtol=1e-5, equal_nan=True)
    np.testing.assert_array_equal(shipped["frames"], original["frames"])  # integers stay exact


def test_a_long_log_ships_thinned_with_every_evaluation_and_the_same_run_clock(tmp_path: Path) -> None:
    from crisp_gym.policy.files import run_wall_time
    from crisp_gym.train.ship import read_progress, thin_progress, write_progress

    rows = 10_007  # two segments: a run stopped after 6,002 iterations (not a multiple of the stride) and resumed
    time_s = np.r_[np.arange(6002) * 0.5 + 3.0, np.arange(4005) * 0.25 + 7.0]
    evaluated = np.arange(rows) % 100 == 37
    log = {"iteration": np.arange(rows, dtype=float), "frames": np.arange(1, rows + 1) * 1024.0, "time_s": time_s,
           "success_rate": np.random.default_rng(0).random(rows),
           "eval_success/walk": np.where(evaluated, 0.5, np.nan), "confirm_success/walk": np.full(rows, np.nan)}
    log["confirm_success/walk"][-3] = 0.9
    write_progress(log, tmp_path / "whole.csv")

    thin = thin_progress(read_progress(tmp_path / "whole.csv"), 2000)
    assert list(thin) == list(log)
    assert 1000 < len(thin["frames"]) <= 2000 + evaluated.sum() + 4  # evenly spaced, at most 2000, + evaluations
    kept = thin["iteration"].astype(int)
    assert np.all(np.diff(kept) > 0) and kept[0] == 0 and kept[-1] == rows - 1
    assert np.diff(kept).max() <= 6  # evenly spaced: at most every 6th iteration missing
    assert set(np.flatnonzero(evaluated)) <= set(kept) and rows - 3 in kept
    for key in log:  # the rows kept are the log's own rows
        np.testing.assert_allclose(thin[key], log[key][kept], rtol=1e-5, equal_nan=True)
    write_progress(thin, tmp_path / "thin.csv")
    assert run_wall_time(tmp_path / "thin.csv") == pytest.approx(run_wall_time(tmp_path / "whole.csv"))
    assert run_wall_time(tmp_path / "whole.csv") == pytest.approx(6001 * 0.5 + 3.0 + 4004 * 0.25 + 7.0)
    short = {key: column[:500] for key, column in log.items()}
    assert thin_progress(short, 2000) is short and thin_progress(log, 0) is log


def test_join_videos_plays_the_clips_in_order_with_captions(tmp_path: Path) -> None:
    import imageio.v2 as imageio

    from crisp_gym.train.demo import join_videos

    videos = {}
    for name, shade, count in (("first", 40, 5), ("second", 200, 3)):
        videos[name] = tmp_path / f"{name}.mp4"
        imageio.mimwrite(videos[name], [np.full((64, 96, 3), shade, np.uint8)] * count, fps=30, macro_block_size=8)
    join_videos(videos, tmp_path / "all.mp4")
    frames = np.stack(imageio.mimread(tmp_path / "all.mp4"))
    assert len(frames) == 8
    lower = frames[:, 48:].mean(axis=(1, 2, 3))  # below the caption: the clip's own shade
    assert np.all(np.abs(lower[:5] - 40) < 8) and np.all(np.abs(lower[5:] - 200) < 8)
    assert frames[0, 10:45, 10:90].max() > 150  # white caption text on the dark first clip


def test_shipped_policy_of_a_clip_is_its_own_or_a_library_policy_listing_it(tmp_path: Path, monkeypatch) -> None:
    from crisp_gym.train import demo

    for name, clips in (("flat_walk", None), ("library", ["stairs_up", "chair_sit"])):
        (tmp_path / name).mkdir()
        (tmp_path / name / "policy.pt").write_bytes(b"")
        if clips:
            (tmp_path / name / "eval.json").write_text(json.dumps({"clips": {c: {} for c in clips}}))
    monkeypatch.setattr(demo, "SHIPPED_POLICIES", tmp_path)
    assert demo.shipped_policy("flat_walk") == tmp_path / "flat_walk" / "policy.pt"
    assert demo.shipped_policy("chair_sit") == tmp_path / "library" / "policy.pt"
    assert demo.shipped_policy("stairs_down") is None
