"""Tests of the PPO trainer (``train/``): models, normaliser, env adapter, training, checkpoints.

Everything runs on a small synthetic clip written into a temporary directory, with a few
envs, short roll-outs and small networks, so the module takes well under a few minutes on
two CPU cores.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from crisp_gym.policy.model_config import ModelConfig
from crisp_gym.policy.networks import (
    ACTION_DIM,
    PROPRIO_DIM,
    TARGET_DIM,
    Critic,
    FixedStdGaussian,
    ObsNormalizer,
    RunningMeanStd,
    TransformerActor,
    build_actor,
)

K, N_POINTS = 5, 128
TINY_TRANSFORMER = ModelConfig(latent_dim=32, ff_dim=64, critic_hidden=(64, 64), pointnet_hidden=(16, 32))
SMALL_MLP = ModelConfig(actor="mlp", mlp_actor_hidden=(128, 128), critic_hidden=(256, 256),
                        pointnet_hidden=(16, 32))
EVAL_START_FRAMES = list(range(0, 80, 8))


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory) -> Path:
    """A 3 s clip: walking forward at 0.2 m/s, swinging an arm and bending a knee, with a step box ahead."""
    from crisp_gym.clip import write_clip
    from crisp_gym.humanoid import DOF_NAMES, build_humanoid
    from crisp_gym.motion import Motion, ground
    from crisp_gym.scene import Box, floor_box

    frames = 90
    t = np.arange(frames) / 30.0
    dof = np.zeros((frames, len(DOF_NAMES)))
    dof[:, DOF_NAMES.index("L_Shoulder_x")] = -1.2 + 0.3 * np.sin(2 * t)
    dof[:, DOF_NAMES.index("R_Shoulder_x")] = 1.2
    dof[:, DOF_NAMES.index("L_Knee_y")] = 0.2 * (1 - np.cos(2 * t))
    dof[:, DOF_NAMES.index("L_Hip_y")] = -0.1 * (1 - np.cos(2 * t))
    motion = Motion(fps=30, root_pos=np.c_[0.2 * t, np.zeros(frames), np.ones(frames)],
                    root_quat=np.tile([1.0, 0, 0, 0], (frames, 1)), dof_pos=dof)
    motion = ground(motion, build_humanoid())
    directory = tmp_path_factory.mktemp("clip") / "walk"
    boxes = [floor_box(), Box(center=[2.0, 0.0, 0.1], half_size=[0.3, 0.5, 0.1])]
    write_clip(directory, boxes, motion, {"source": "test"})
    return directory


def _obs(batch: tuple[int, ...], scene_aware: bool, seed: int = 0) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    obs = [torch.randn(*batch, PROPRIO_DIM, generator=g), torch.randn(*batch, K, TARGET_DIM, generator=g)]
    if scene_aware:
        obs.append(torch.randn(*batch, N_POINTS, 3, generator=g))
    return obs


# ----------------------------------------------------------------------------- models


@pytest.mark.parametrize("actor", ["transformer", "mlp"])
@pytest.mark.parametrize("scene_aware, points", [(False, "pointnet"), (True, "pointnet"), (True, "flat")],
                         ids=["blind", "pointnet", "flat"])
def test_model_shapes(actor: str, scene_aware: bool, points: str) -> None:
    config = replace(ModelConfig(), actor=actor, point_encoder=points)
    normalizer = ObsNormalizer(K)
    policy = FixedStdGaussian(build_actor(config, K, N_POINTS if scene_aware else 0, normalizer), config.action_std)
    critic = Critic(K, N_POINTS if scene_aware else 0, normalizer, config.critic_hidden)
    obs = _obs((2, 3), scene_aware)
    loc, scale = policy(*obs)
    assert loc.shape == scale.shape == (2, 3, ACTION_DIM)
    assert torch.all(scale == 0.055)
    assert critic(*obs).shape == (2, 3, 1)
    # leading batch dimensions are independent: a flat batch gives the same numbers
    flat = [x.reshape(6, *x.shape[2:]) for x in obs]
    torch.testing.assert_close(policy(*flat)[0], loc.reshape(6, ACTION_DIM))
    # the untrained policy's residual actions start near zero
    assert loc.abs().max() < 0.1
    if scene_aware:
        with pytest.raises(ValueError, match="points"):
            policy(*obs[:2])


def test_flat_points_is_a_linear_map_of_the_points_in_their_order() -> None:
    from crisp_gym.policy.networks import FlatPoints

    encoder = FlatPoints(2, 3)
    with torch.no_grad():
        encoder.linear.weight.copy_(torch.arange(18.0).reshape(3, 6) / 10)
        encoder.linear.bias.copy_(torch.tensor([0.0, -1.0, -30.0]))
    points = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]]])
    # flattened [1, 0, 0, 0, 0, 2]: each row of W takes its first and its last entry (x2)
    pre = torch.tensor([[0.0 + 2 * 0.5 + 0.0, 0.6 + 2 * 1.1 - 1.0, 1.2 + 2 * 1.7 - 30.0]])
    torch.testing.assert_close(encoder(points), torch.nn.functional.elu(pre))
    assert not torch.equal(encoder(points.flip(1)), encoder(points))  # each slot has its own weights
    with pytest.raises(ValueError, match=r"\(2, 3\) points"):
        encoder(torch.zeros(1, 3, 3))
    with pytest.raises(ValueError, match="point_encoder"):
        ModelConfig(point_encoder="voxels")


def test_output_layers_compute_in_float32_under_bfloat16_autocast() -> None:
    from torch import nn

    from crisp_gym.policy.networks import Float32Linear

    torch.manual_seed(0)
    exact, plain = Float32Linear(256, 69), nn.Linear(256, 69)
    plain.load_state_dict(exact.state_dict())  # the same keys: files load either way
    hidden = torch.randn(32, 256).bfloat16()  # what a bfloat16 hidden layer hands over
    expected = torch.nn.functional.linear(hidden.float(), exact.weight, exact.bias)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out, rounded = exact(hidden), plain(hidden)
    assert out.dtype == torch.float32 and rounded.dtype == torch.bfloat16
    torch.testing.assert_close(out, expected, rtol=0, atol=0)
    assert (rounded.float() - expected).abs().max() > 1e-4  # what it avoids: bfloat16's rounding

    # the whole actor and critic: float32 outputs within bfloat16's rounding of the float32 pass
    model = replace(SMALL_MLP, init_action_std=0.05)  # action means of O(0.1), not ~0
    normalizer = ObsNormalizer(K)
    actor, critic = build_actor(model, K, 0, normalizer), Critic(K, 0, normalizer, model.critic_hidden)
    obs = _obs((256,), False)
    with torch.no_grad():
        loc, value = actor(*obs), critic(*obs)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            loc_bf16, value_bf16 = actor(*obs), critic(*obs)
    assert loc_bf16.dtype == value_bf16.dtype == torch.float32
    assert (loc_bf16 - loc).abs().max() < 0.05 * loc.abs().mean()
    assert (value_bf16 - value).abs().max() < 0.05 * value.abs().mean()


def test_files_from_before_the_point_encoder_option_load() -> None:
    """Actors saved when the encoder was always a PointNet named it ``pointnet``."""
    normalizer = ObsNormalizer(K)
    saved = build_actor(SMALL_MLP, K, N_POINTS, normalizer).state_dict()
    old = {k.replace("point_encoder.", "pointnet."): v for k, v in saved.items()}
    assert any(k.startswith("pointnet.") for k in old)
    actor = build_actor(SMALL_MLP, K, N_POINTS, ObsNormalizer(K))
    actor.load_state_dict(old)
    reference = build_actor(SMALL_MLP, K, N_POINTS, ObsNormalizer(K))
    reference.load_state_dict(saved)
    obs = _obs((4,), True, seed=3)
    torch.testing.assert_close(actor(*obs), reference(*obs), rtol=0, atol=0)


def test_saved_configs_read_back_and_damaged_ones_say_what_is_wrong(tmp_path: Path) -> None:
    """A config round-trips; one written before a key existed takes that key's default; a key
    with a damaged name, or no ``output``, is a ValueError naming it (it was a KeyError)."""
    from crisp_gym.train.config import TrainConfig, config_from_dict, config_to_dict

    cfg = TrainConfig(output=tmp_path / "run", clip=("flat_walk", "stairs_up"), confirm_episodes=7)
    saved = config_to_dict(cfg)
    assert config_from_dict(saved) == cfg
    older = {k: v for k, v in saved.items() if k != "confirm_episodes"}
    assert config_from_dict(older).confirm_episodes == TrainConfig(output=tmp_path).confirm_episodes
    damaged = {("nutput" if k == "output" else k): v for k, v in saved.items()}
    with pytest.raises(ValueError, match=r"unknown keys \['nutput'\]; no output"):
        config_from_dict(damaged)
    with pytest.raises(ValueError, match="model settings"):
        config_from_dict({**saved, "model": {**saved["model"], "hiddn": 3}})


def test_transformer_tokens_and_paper_size() -> None:
    config = ModelConfig(num_point_tokens=2)
    actor = TransformerActor(K, N_POINTS, ObsNormalizer(K), config)
    proprio, targets, points = _obs((4,), True)
    tokens = actor.tokens(proprio, targets, points)
    assert tokens.shape == (4, 1 + K + 2, 256)  # proprio + one per target frame + point tokens
    layer = actor.encoder.layers[0]
    assert len(actor.encoder.layers) == 2
    assert layer.self_attn.num_heads == 2 and layer.linear1.out_features == 512
    critic = Critic(K, 0, ObsNormalizer(K))
    assert [m.out_features for m in critic.net if isinstance(m, torch.nn.Linear)] == [1024, 512, 1]


def test_running_mean_std_matches_numpy() -> None:
    rng = np.random.default_rng(0)
    batches = [rng.normal(loc=3.0, scale=s, size=(n, 4, 6)) for n, s in [(7, 0.5), (100, 2.0), (1, 1.0), (33, 4.0)]]
    stats = RunningMeanStd((4, 6), clip=1e9)
    for b in batches:
        stats.update(torch.as_tensor(b, dtype=torch.float32))
    data = np.concatenate(batches).astype(np.float32).astype(np.float64)
    np.testing.assert_allclose(stats.mean.numpy(), data.mean(axis=0), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(stats.var.numpy(), data.var(axis=0), rtol=1e-9)
    assert stats.count.item() == len(data)
    normalised = stats(torch.as_tensor(data, dtype=torch.float32)).double().numpy()
    np.testing.assert_allclose(normalised.mean(axis=0), 0.0, atol=1e-5)
    np.testing.assert_allclose(normalised.std(axis=0), 1.0, atol=1e-4)
    # clipping
    clipped = RunningMeanStd(3, clip=2.0)
    assert clipped(torch.tensor([100.0, -100.0, 0.5])).tolist() == pytest.approx([2.0, -2.0, 0.5], abs=1e-4)


def test_limited_statistics_weigh_new_data_as_if_that_many_samples_had_been_seen() -> None:
    rng = np.random.default_rng(1)
    old = rng.normal(0.0, 0.01, size=(100_000, 3))  # e.g. arms that barely moved
    new = rng.normal(2.0, 1.0, size=(500, 3))
    stats = RunningMeanStd(3, clip=1e9)
    stats.update(torch.as_tensor(old))
    stats.limit_count(1_000)
    stats.update(torch.as_tensor(new))
    expected = (1_000 * old.mean(axis=0) + 500 * new.mean(axis=0)) / 1_500
    np.testing.assert_allclose(stats.mean.numpy(), expected, rtol=1e-9)
    assert stats.count.item() == 1_500
    stats.limit_count(1e9)  # a limit above the count changes nothing
    assert stats.count.item() == 1_500
    from crisp_gym.train.config import TrainConfig

    with pytest.raises(ValueError, match="init_stats_samples"):
        TrainConfig(init_stats_samples=0)


def test_obs_normalizer_is_shared_and_saved() -> None:
    normalizer = ObsNormalizer(K)
    actor = build_actor(SMALL_MLP, K, 0, normalizer)
    critic = Critic(K, 0, normalizer, SMALL_MLP.critic_hidden)
    proprio, targets = _obs((50,), False)
    normalizer.update(proprio * 3 + 1, targets)
    assert torch.equal(actor.state_dict()["normalizer.proprio.mean"], critic.state_dict()["normalizer.proprio.mean"])
    assert actor.state_dict()["normalizer.proprio.count"].item() == 50


def test_normalize_advantages() -> None:
    from crisp_gym.train.ppo import normalize_advantages

    advantage = torch.randn(4096, 1, generator=torch.Generator().manual_seed(1)) * 37.0 + 12.0
    normalised = normalize_advantages(advantage)
    assert normalised.shape == advantage.shape
    assert abs(normalised.mean().item()) < 1e-5
    assert normalised.std(unbiased=False).item() == pytest.approx(1.0, abs=1e-5)
    assert torch.equal(normalize_advantages(torch.tensor([[5.0]])), torch.tensor([[0.0]]))


# ----------------------------------------------------------------------------- env adapter


def test_training_reward_caps_the_energy_penalty_and_scales() -> None:
    from crisp_gym.train.env import TrainingReward

    terms = {"pos": np.array([2.0, 1.0, 0.5]), "energy": np.array([-0.1, -3.0, np.nan])}
    reward = np.array([2.0 - 0.1, 1.0 - 3.0, 0.0])  # a non-finite state gets reward 0 from the env
    assert TrainingReward().is_identity
    np.testing.assert_allclose(TrainingReward()(reward, terms), reward)
    capped = TrainingReward(scale=0.5, energy_cap=0.5)
    assert not capped.is_identity
    # below the cap unchanged; above it the penalty is -0.5; a NaN term leaves the reward alone
    np.testing.assert_allclose(capped(reward, terms), 0.5 * np.array([1.9, 1.0 - 0.5, 0.0]))
    with pytest.raises(ValueError):
        TrainingReward(scale=0.0)
    with pytest.raises(ValueError):
        TrainingReward(energy_cap=-1.0)



def test_env_adapter_specs_and_final_observations(clip_dir: Path) -> None:
    from torchrl.envs.utils import check_env_specs

    from crisp_gym.train.config import paper_profile
    from crisp_gym.train.ppo import make_env

    env = make_env(paper_profile(clip=str(clip_dir), num_envs=4, scene_aware=True), seed=0)
    check_env_specs(env)
    rollout = env.rollout(60, policy=lambda td: td.set("action", torch.zeros(4, ACTION_DIM)),
                          break_when_any_done=False)
    done = rollout["next", "done"].squeeze(-1)
    assert done.any(), "the clip is 90 frames long: some episodes must end within 60 steps"
    env_id, step = [int(i) for i in done.nonzero()[0]]
    # "next" holds the episode's last observation, the following root the next episode's first
    last, first = rollout["next", "proprio"][env_id, step], rollout["proprio"][env_id, step + 1]
    assert not torch.allclose(last, first)
    assert rollout["episode_length"][env_id, step + 1].item() == 0
    assert rollout["next", "episode_length"][env_id, step].item() >= 1
    env.close()


def test_single_pass_values_match_torchrl_gae(clip_dir: Path) -> None:
    """``estimate_values`` + value-less GAE gives TorchRL's two-pass GAE, episode ends included."""
    from torchrl.objectives.value import GAE

    from crisp_gym.train.config import paper_profile
    from crisp_gym.train.ppo import build_agent, estimate_values, make_env

    env = make_env(paper_profile(clip=str(clip_dir), num_envs=4), seed=1)
    agent = build_agent(SMALL_MLP, env.observation_spec["targets"].shape[-2], 0)
    with torch.no_grad():
        rollout = env.rollout(50, policy=agent.policy, break_when_any_done=False)
        env.close()
        assert rollout["next", "done"][:, :-1].any(), "the test needs episode ends inside the batch"
        reference = GAE(gamma=0.99, lmbda=0.95, value_network=agent.value, average_gae=False)(rollout.clone())
        ours = rollout.clone()
        estimate_values(ours, agent.value)
        GAE(gamma=0.99, lmbda=0.95, value_network=None, average_gae=False)(ours)
    for key in ("state_value", ("next", "state_value"), "advantage", "value_target"):
        torch.testing.assert_close(ours[key], reference[key], rtol=1e-5, atol=1e-5)


# ----------------------------------------------------------------------------- training


def _progress_rows(path: Path) -> list[dict[str, str]]:
    """A run's ``progress.csv`` as its rows, read as a user would (strings, empty cells kept)."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _tiny_config(clip_dir: Path, output: Path, **overrides) -> "TrainConfig":  # noqa: F821
    from crisp_gym.train.config import cpu_profile

    # unscaled rewards: the learning rates here suit the critic regressing the env's own returns
    base = dict(clip=str(clip_dir), output=output, num_envs=16, steps_per_env=32, minibatch_size=256, epochs=4,
                actor_lr=1e-4, critic_lr=1e-3, reward_scale=1.0, model=SMALL_MLP, checkpoint_every=4, progress=False,
                seed=3, torch_threads=2, collector_workers=0)  # in this process: tests patch its env and trainer
    return cpu_profile(**{**base, **overrides})


@pytest.fixture(scope="module")
def trained_run(clip_dir: Path, tmp_path_factory):
    """A run started from a deliberately biased policy, evaluated before and after ~4K frames.

    The untrained policy's residual actions are near zero, which already tracks the reference
    fairly well; adding 0.05 rad to every action makes it clearly worse, so a few thousand
    frames of PPO must show a measurable improvement.
    """
    from crisp_gym.policy.files import load_checkpoint
    from crisp_gym.train.checkpoints import load_policy
    from crisp_gym.train.ppo import train
    from crisp_gym.train.rollouts import evaluate

    output = tmp_path_factory.mktemp("run")
    cfg = _tiny_config(clip_dir, output, frames=0)
    assert train(cfg).iteration == 0
    state = load_checkpoint(output)
    state["actor"]["actor.net.4.bias"] += 0.05  # the MLP's action head
    torch.save(state, output / "checkpoint.pt")
    before = evaluate(load_policy(output)[0], clip_dir, EVAL_START_FRAMES)
    result = train(replace(cfg, frames=4096, resume=True))
    after = evaluate(load_policy(output)[0], clip_dir, EVAL_START_FRAMES)
    return cfg, result, before, after


def test_training_losses_are_finite_and_critic_learns(trained_run) -> None:
    _, result, _, _ = trained_run
    assert result.frames == 4096 and result.iteration == 8
    updates = [row for row in result.history if "loss_critic" in row]
    assert len(updates) == 7  # the first batch only initialises the observation statistics
    for row in updates:
        for key in ("loss_objective", "loss_critic", "kl_approx", "clip_fraction"):
            assert np.isfinite(row[key]), (key, row)
    critic_losses = [row["loss_critic"] for row in updates]
    assert np.mean(critic_losses[-3:]) < 0.5 * critic_losses[0]
    assert updates[-1]["explained_variance"] > 0.3
    assert all(abs(row["loss_objective"]) < 1.0 for row in updates)  # normalised advantages, clipped ratios
    assert any(row["episodes"] > 0 for row in result.history)


def test_policy_improves_on_fixed_start_frames(trained_run) -> None:
    _, _, before, after = trained_run
    assert len(before.returns) == len(EVAL_START_FRAMES)
    assert after.mean_return > before.mean_return + 3.0, (before.mean_return, after.mean_return)


def test_progress_csv_and_config(trained_run) -> None:
    cfg, result, _, _ = trained_run
    rows = _progress_rows(Path(cfg.output) / "progress.csv")
    assert [int(r["iteration"]) for r in rows] == list(range(1, 9))
    assert int(rows[-1]["frames"]) == result.frames
    assert (Path(cfg.output) / "config.json").is_file()
    assert not list(Path(cfg.output).glob("*.tmp*"))


def test_checkpoint_round_trip_and_resume(trained_run, tmp_path: Path) -> None:
    from crisp_gym.policy.files import load_checkpoint
    from crisp_gym.train.checkpoints import load_policy
    from crisp_gym.train.ppo import train

    cfg, result, _, _ = trained_run
    state = load_checkpoint(cfg.output)
    assert state["iteration"] == result.iteration and state["frames"] == result.frames
    # identical outputs after a save/load round trip (weights and normaliser statistics)
    policy_a, loaded_cfg = load_policy(cfg.output)
    policy_b, _ = load_policy(cfg.output)
    assert loaded_cfg == replace(cfg, frames=result.frames, resume=True)
    obs = _obs((8,), False, seed=5)
    torch.testing.assert_close(policy_a(*obs)[0], policy_b(*obs)[0], rtol=0, atol=0)
    assert policy_a.actor.normalizer.proprio.count.item() > 0
    # resuming continues the iteration and frame counts
    resumed = train(replace(cfg, frames=result.frames + cfg.frames_per_iteration, resume=True))
    assert resumed.iteration == result.iteration + 1
    assert resumed.frames == result.frames + cfg.frames_per_iteration
    assert len(resumed.history) == 1
    # a fresh run refuses to overwrite a checkpoint; resuming with another architecture is an error
    with pytest.raises(FileExistsError):
        train(replace(cfg, resume=False))
    with pytest.raises(ValueError, match="model"):
        train(replace(cfg, resume=True, model=TINY_TRANSFORMER))
    with pytest.raises(FileNotFoundError):
        train(replace(cfg, output=tmp_path / "nothing", resume=True))


def test_resuming_compares_only_what_the_networks_are_built_from(tmp_path: Path) -> None:
    """A scene-blind run has no point encoder: a profile that changes it still resumes the run
    (and warm-starts from its policy); a scene-aware run is refused, naming the option."""
    from crisp_gym.train.checkpoints import check_resumable
    from crisp_gym.train.config import cpu_profile

    pointnet = replace(cpu_profile(), model=replace(cpu_profile().model, point_encoder="pointnet"))
    flat = replace(pointnet, model=replace(pointnet.model, point_encoder="flat", latent_dim=64))
    check_resumable(pointnet, flat)  # blind MLP: neither the encoder nor the transformer's width builds anything
    with pytest.raises(ValueError, match=r"model.point_encoder differ.*model.point_encoder='pointnet'"):
        check_resumable(replace(pointnet, scene_aware=True), replace(flat, scene_aware=True))
    with pytest.raises(ValueError, match="model.mlp_actor_hidden"):
        check_resumable(pointnet, replace(pointnet, model=replace(pointnet.model, mlp_actor_hidden=(64,))))
    with pytest.raises(ValueError, match="scene_aware"):
        check_resumable(pointnet, replace(pointnet, scene_aware=True))


@pytest.mark.parametrize("model, num_points", [(TINY_TRANSFORMER, N_POINTS),
                                               (replace(SMALL_MLP, point_encoder="flat"), 48)],
                         ids=["pointnet", "flat"])
def test_save_load_agent_exact(model: ModelConfig, num_points: int, tmp_path: Path) -> None:
    from crisp_gym.train.checkpoints import load_policy, save_checkpoint
    from crisp_gym.train.config import paper_profile
    from crisp_gym.train.ppo import build_agent

    cfg = paper_profile(output=tmp_path, scene_aware=True, model=model)
    agent = build_agent(cfg.model, K, num_points)
    agent.normalizer.update(*_obs((64,), False, seed=2))
    optimizer = torch.optim.Adam(agent.actor.parameters())
    save_checkpoint(tmp_path / "checkpoint.pt", agent, optimizer, 7, 1234, cfg, torch.Generator())
    loaded, loaded_cfg = load_policy(tmp_path)  # a flat encoder's point count comes back from its weights
    assert loaded_cfg == cfg
    obs = _obs((3,), False, seed=9) + [torch.randn(3, num_points, 3, generator=torch.Generator().manual_seed(9))]
    torch.testing.assert_close(loaded(*obs)[0], agent.actor(*obs)[0], rtol=0, atol=0)


def test_scene_aware_transformer_trains(clip_dir: Path, tmp_path: Path) -> None:
    from crisp_gym.train.ppo import train

    cfg = _tiny_config(clip_dir, tmp_path, scene_aware=True, model=TINY_TRANSFORMER, num_envs=4, frames=512,
                       minibatch_size=64, epochs=1)
    result = train(cfg)
    assert result.iteration == 4
    assert all(np.isfinite(row["loss_critic"]) for row in result.history if "loss_critic" in row)


def test_training_in_bfloat16(clip_dir: Path, tmp_path: Path) -> None:
    from crisp_gym.train.config import config_from_dict
    from crisp_gym.train.ppo import train

    with pytest.raises(ValueError, match="precision"):
        _tiny_config(clip_dir, tmp_path, precision="float16")
    cfg = _tiny_config(clip_dir, tmp_path, precision="bfloat16", num_envs=8, frames=2048, minibatch_size=128, epochs=1)
    result = train(cfg)
    updates = [row for row in result.history if "loss_critic" in row]
    assert len(updates) == 7 and all(np.isfinite(row["loss_critic"]) for row in updates)
    assert config_from_dict(json.loads((tmp_path / "config.json").read_text())).precision == "bfloat16"


def test_bfloat16_only_where_the_cpu_multiplies_it_natively(clip_dir: Path, tmp_path: Path, monkeypatch) -> None:
    import crisp_gym.train.config as config
    import crisp_gym.train.ppo as ppo

    for native, expected in ((True, "bfloat16"), (False, "float32")):
        monkeypatch.setattr(config, "native_bfloat16", lambda native=native: native)
        assert config.cpu_profile().precision == expected
    # asked for anyway on such a CPU, the run says that it will be slow
    monkeypatch.setattr(ppo, "native_bfloat16", lambda: False)
    with pytest.warns(UserWarning, match="emulates"):
        ppo.train(_tiny_config(clip_dir, tmp_path, precision="bfloat16", frames=0))


def test_cpu_flags_answer_as_torchs_own_probes(tmp_path: Path) -> None:
    from crisp_gym.train.cli import cuda_available
    from crisp_gym.train.config import linux_cpu_flags, native_bfloat16

    (tmp_path / "cpuinfo").write_text("processor\t: 0\nflags\t\t: fpu sse2 avx512_bf16\n\nprocessor\t: 1\n"
                                      "flags\t\t: fpu\n")
    assert linux_cpu_flags(tmp_path / "cpuinfo") == {"fpu", "sse2", "avx512_bf16"}
    assert linux_cpu_flags(tmp_path / "missing") is None
    probes = torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported()
    assert native_bfloat16() == probes
    assert cuda_available() == torch.cuda.is_available()


def test_train_help_does_not_import_torch() -> None:
    from crisp_gym.train.cli import cuda_available

    if cuda_available() or sys.platform != "linux":
        pytest.skip("asking CUDA for the 'auto' profile needs torch here")
    code = ("import sys\nfrom crisp_gym import cli\ntry:\n    cli.main(['train', '--help'])\nexcept SystemExit:\n"
            "    pass\nprint('torch' in sys.modules, 'mujoco' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "--model.action-std" in out  # the whole help, profile defaults included
    assert out.split()[-2:] == ["False", "False"]


def test_cli(clip_dir: Path, tmp_path: Path) -> None:
    from crisp_gym.train.cli import main

    out = tmp_path / "cli"
    assert main(["--profile", "cpu", "--clip", str(clip_dir), "--scene-aware", "--frames", "64", "--num-envs", "2",
                 "--steps-per-env", "32", "-o", str(out), "--no-progress", "--model.mlp-actor-hidden", "32",
                 "--model.critic-hidden", "32"]) == 0
    assert (out / "checkpoint.pt").is_file() and (out / "config.json").is_file()
    with pytest.raises(SystemExit):
        main(["--profile", "nope"])


def test_interrupt_saves_checkpoint(clip_dir: Path, tmp_path: Path) -> None:
    from crisp_gym.policy.files import load_checkpoint
    from crisp_gym.train.ppo import make_env, train

    def env_fn(cfg, seed):
        env = make_env(cfg, seed)
        step, calls = env.vec_env.step, []

        def interrupting_step(actions):
            calls.append(1)
            if len(calls) == 3 * cfg.steps_per_env + 5:  # Ctrl-C during the fourth collection
                raise KeyboardInterrupt
            return step(actions)
        env.vec_env.step = interrupting_step
        return env

    cfg = _tiny_config(clip_dir, tmp_path, num_envs=2, frames=10**6, checkpoint_every=100)
    result = train(cfg, env_fn=env_fn)
    assert result.interrupted and result.iteration == 3
    assert load_checkpoint(tmp_path)["iteration"] == 3
    assert not list(tmp_path.glob("*.tmp*"))


def test_resumed_log_drops_iterations_after_the_checkpoint(tmp_path: Path) -> None:
    from crisp_gym.policy.files import run_wall_time
    from crisp_gym.train.run_log import RunLogger

    logger = RunLogger(tmp_path, append=False)
    for i in range(1, 6):
        logger.log({"iteration": i, "frames": 100 * i, "time_s": 10.0 * i})
    logger.close()
    # the run died after iteration 5 with its last checkpoint at 3: resuming logs 4 and 5 again
    logger = RunLogger(tmp_path, append=True, iteration=3)
    logger.log({"iteration": 4, "frames": 400, "time_s": 7.0})
    logger.close()
    rows = _progress_rows(tmp_path / "progress.csv")
    assert [int(r["iteration"]) for r in rows] == [1, 2, 3, 4]
    # the resumed segment's clock restarts: wall time adds the segments (30 s + 7 s)
    assert run_wall_time(tmp_path / "progress.csv") == pytest.approx(37.0)


def test_a_resumed_log_gains_new_columns_but_not_other_clips(tmp_path: Path) -> None:
    """A log from a version with fewer columns is rewritten with the new ones (old rows keep
    their values, empty in the new columns); a log of other clips is refused."""
    from crisp_gym.train.run_log import RunLogger

    old = RunLogger(tmp_path, append=False, extra_fields=("start_failures/a",))
    old.log({"iteration": 1, "frames": 100, "start_failures/a": 2.5})
    old.close()
    new = RunLogger(tmp_path, append=True, iteration=1, extra_fields=("start_failures/a", "clip_probability/a"))
    new.log({"iteration": 2, "frames": 200, "start_failures/a": 1.0, "clip_probability/a": 1.0})
    new.close()
    with open(tmp_path / "progress.csv", newline="") as f:
        reader = csv.DictReader(f)
        rows, header = list(reader), reader.fieldnames
    assert header[-1] == "clip_probability/a"
    assert [(r["start_failures/a"], r["clip_probability/a"]) for r in rows] == [("2.5", ""), ("1.0", "1.0")]
    with pytest.raises(ValueError, match="clips the run started with"):
        RunLogger(tmp_path, append=True, iteration=2, extra_fields=("start_failures/b",))
    with pytest.raises(ValueError, match="clips the run started with"):  # an added clip is no newer version
        RunLogger(tmp_path, append=True, iteration=2,
                  extra_fields=("start_failures/a", "start_failures/b", "clip_probability/a", "clip_probability/b"))


def test_resume_applies_the_configured_learning_rates(clip_dir: Path, tmp_path: Path) -> None:
    from crisp_gym.policy.files import load_checkpoint
    from crisp_gym.train.ppo import train

    cfg = _tiny_config(clip_dir, tmp_path, num_envs=4, frames=256, actor_lr=1e-4, critic_lr=1e-3)
    train(cfg)
    train(replace(cfg, frames=512, actor_lr=3e-5, critic_lr=2e-4, resume=True))
    groups = load_checkpoint(tmp_path)["optimizer"]["param_groups"]
    assert [g["lr"] for g in groups] == [3e-5, 2e-4]


def test_warm_start_loads_the_actor_and_trains_the_critic_first(clip_dir: Path, tmp_path: Path) -> None:
    """``init_from`` a policy file: the new run starts from its actor (normaliser included, so no
    iteration only gathers statistics); during the critic warm-up only the critic moves; after
    it the actor trains; a different architecture is refused."""
    from crisp_gym.policy.files import load_checkpoint, write_policy_file
    from crisp_gym.train.ppo import train

    source = tmp_path / "source"
    train(_tiny_config(clip_dir, source, num_envs=4, frames=512))
    policy = write_policy_file(source, tmp_path / "shipped")
    original = load_checkpoint(source)["actor"]
    weights = [k for k in original if "normalizer" not in k]

    warm = _tiny_config(clip_dir, tmp_path / "warm", num_envs=4, frames=3 * 128, init_from=policy, critic_warmup=3)
    result = train(warm)
    assert len(result.history) == 3 and all("loss_critic" in row for row in result.history)
    held = load_checkpoint(warm.output)["actor"]
    for key in weights:
        torch.testing.assert_close(held[key], original[key], rtol=0, atol=0, msg=key)

    trained = train(replace(warm, output=tmp_path / "warm2", critic_warmup=1))
    moved = load_checkpoint(trained.checkpoint)["actor"]
    assert any(not torch.equal(moved[k], original[k]) for k in weights)
    with pytest.raises(ValueError, match="cannot initialise from"):
        train(replace(warm, output=tmp_path / "other", model=TINY_TRANSFORMER))

    # a milestone keeps the critic: the next run starts with both networks and no warm-up
    milestone = write_policy_file(source, tmp_path / "milestone", with_critic=True)
    assert "critic" not in torch.load(policy, weights_only=True)
    resumed = train(replace(warm, output=tmp_path / "from_milestone", init_from=milestone, frames=128))
    assert resumed.history[0]["kl_approx"] != 0.0  # the actor trained in the first iteration


def test_a_warm_start_or_resume_may_change_the_exploration_noise(clip_dir: Path, tmp_path: Path) -> None:
    """``model.action_std`` shapes no weight: a run may start from a policy trained with another σ
    (or resume with one), keeps that policy's weights and explores with its own σ."""
    from crisp_gym.policy.files import load_checkpoint, write_policy_file
    from crisp_gym.train.ppo import train

    source = tmp_path / "source"
    train(_tiny_config(clip_dir, source, num_envs=4, frames=256))
    policy = write_policy_file(source, tmp_path / "shipped")
    wider = replace(SMALL_MLP, action_std=0.15)
    warm = _tiny_config(clip_dir, tmp_path / "warm", num_envs=4, frames=2 * 128, init_from=policy, critic_warmup=2,
                        model=wider)
    train(warm)
    original, held = load_checkpoint(source)["actor"], load_checkpoint(warm.output)["actor"]
    assert float(original["std"]) == pytest.approx(SMALL_MLP.action_std) and float(held["std"]) == pytest.approx(0.15)
    for key in original:
        if key != "std" and "normalizer" not in key:
            torch.testing.assert_close(held[key], original[key], rtol=0, atol=0, msg=key)
    train(replace(warm, frames=3 * 128, resume=True, model=replace(wider, action_std=0.1)))
    assert float(load_checkpoint(warm.output)["actor"]["std"]) == pytest.approx(0.1)


def test_periodic_evaluation_is_logged_and_plotted(clip_dir: Path, tmp_path: Path) -> None:
    from crisp_gym.train.ppo import train

    cfg = _tiny_config(clip_dir, tmp_path, num_envs=4, frames=4 * 128, eval_every=2, eval_episodes=4)
    result = train(cfg)
    rows = _progress_rows(tmp_path / "progress.csv")
    evaluated = [r for r in rows if r["eval_success_min"]]
    assert [int(r["iteration"]) for r in evaluated] == [2, 4] and result.iteration == 4
    for r in evaluated:
        assert float(r[f"eval_success/{clip_dir.name}"]) in (0, 0.25, 0.5, 0.75, 1.0)
        assert 0 < int(r[f"eval_frames/{clip_dir.name}"]) <= 89
    assert (tmp_path / "evaluation.png").is_file()


def test_until_success_stops_at_the_first_evaluation_that_meets_it(clip_dir: Path, tmp_path: Path,
                                                                    monkeypatch) -> None:
    """The stop rule reads the evaluation: every clip at the success threshold *and* tracked from
    frame 0 to its end (evaluations replaced by a script, so the rule is tested, not learning)."""
    from crisp_gym.train import rollouts
    from crisp_gym.train.ppo import train

    script = iter([{"success": 0.95, "frames": 40, "num_frames": 90, "whole_clip": False},  # frame 0 fails
                   {"success": 0.85, "frames": 89, "num_frames": 90, "whole_clip": True},   # below the threshold
                   {"success": 0.90, "frames": 89, "num_frames": 90, "whole_clip": True}])  # met

    def scripted(self, policy):
        return {name: next(script) for name in self.names}
    monkeypatch.setattr(rollouts.LibraryEvaluation, "__call__", scripted)
    cfg = _tiny_config(clip_dir, tmp_path, num_envs=4, frames=100 * 128, eval_every=1, eval_episodes=2,
                       until_success=0.9, confirm_episodes=0)
    result = train(cfg)
    assert result.reached_success and result.iteration == 3


def test_until_success_stops_only_once_other_starts_confirm_it(clip_dir: Path, tmp_path: Path,
                                                               monkeypatch) -> None:
    """An evaluation that meets the rule is repeated on ``confirm_episodes`` other starts; the run
    goes on while those fall short, and logs their success (scripted evaluations again)."""
    from crisp_gym.train import rollouts
    from crisp_gym.train.ppo import train

    met = {"success": 1.0, "frames": 89, "num_frames": 90, "whole_clip": True}
    short = {**met, "success": 0.8}
    periodic = iter([short, met, met, met, met])  # the first evaluation is not confirmed at all
    confirming = iter([short, met])
    calls, starts = [], {}

    def scripted(self, policy):
        confirmation = len(self.clips) == 7 + 1  # 7 RSI starts and frame 0
        starts.setdefault(confirmation, self.frames.tolist())
        calls.append("confirm" if confirmation else "eval")
        return {name: next(confirming if confirmation else periodic) for name in self.names}
    monkeypatch.setattr(rollouts.LibraryEvaluation, "__call__", scripted)
    cfg = _tiny_config(clip_dir, tmp_path, num_envs=4, frames=100 * 128, eval_every=1, eval_episodes=6,
                       until_success=0.9, confirm_episodes=7)
    result = train(cfg)
    assert result.reached_success and result.iteration == 3
    assert calls == ["eval", "eval", "confirm", "eval", "confirm"]
    periodic_starts, confirmation_starts = starts[False], starts[True]
    assert periodic_starts[0] == confirmation_starts[0] == 0  # both also run the clip from frame 0
    assert periodic_starts[1:] != confirmation_starts[1:7]  # other RSI starts
    rows = _progress_rows(tmp_path / "progress.csv")
    assert [r[f"confirm_success/{clip_dir.name}"] for r in rows] == ["", "0.8", "1.0"]
    assert (tmp_path / "evaluation.png").is_file()  # drawn with the confirmations
    # the second evaluation scored as well as the third but failed its confirmation
    from crisp_gym.policy.files import BEST_NAME, load_checkpoint
    assert load_checkpoint(tmp_path / BEST_NAME)["iteration"] == 3
    # resumed without the stop rule, the log keeps its columns
    train(replace(cfg, until_success=None, frames=4 * 128, resume=True))
    rows = _progress_rows(tmp_path / "progress.csv")
    assert [r[f"confirm_success/{clip_dir.name}"] for r in rows] == ["", "0.8", "1.0", ""]


def test_actor_learning_rate_ramps_up_after_the_critic_warmup() -> None:
    from crisp_gym.train.ppo import actor_lr_at

    lrs = [actor_lr_at(i, start=20, ramp=100, lr=3e-5) for i in range(0, 200)]
    assert all(lr == 0 for lr in lrs[:20])
    assert lrs[20] == pytest.approx(3e-7) and lrs[119] == pytest.approx(3e-5) and lrs[199] == pytest.approx(3e-5)
    assert np.all(np.diff(lrs) >= 0)


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_stop_signal_to_a_background_run_saves_its_checkpoint(clip_dir: Path, tmp_path: Path, sig: str) -> None:
    """A run started in the background (SIGINT ignored, as ``cmd &`` does) and stopped with
    SIGTERM or SIGINT writes its checkpoint at the iteration it reached and exits with 130."""
    import signal
    import subprocess
    import sys
    import time

    from crisp_gym.policy.files import load_checkpoint

    out = tmp_path / "run"
    command = [sys.executable, "-m", "crisp_gym.train.cli", "--profile", "cpu", "--clip", str(clip_dir), "-o", str(out),
               "--num-envs", "2", "--steps-per-env", "16", "--checkpoint-every", "1000", "--no-progress",
               "--model.mlp-actor-hidden", "32", "--model.critic-hidden", "32"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and process.poll() is None:
        progress = out / "progress.csv"
        if progress.is_file() and len(progress.read_text().splitlines()) > 3:
            break
        time.sleep(0.2)
    process.send_signal(getattr(signal, sig))
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, stderr.decode()[-2000:]
    rows = _progress_rows(out / "progress.csv")
    assert load_checkpoint(out)["iteration"] == int(rows[-1]["iteration"]) >= 3


def test_a_stop_signal_during_an_update_lands_after_its_log_row(clip_dir: Path, tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """A signal that arrives mid-update stops the run after that iteration's row: the checkpoint's
    iteration is the last row of ``progress.csv``, so a resumed log has no hole."""
    import os
    import signal

    from crisp_gym.policy.files import load_checkpoint
    from crisp_gym.train import ppo

    update, calls = ppo.ppo_update, []

    def update_then_signal(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return update(*args, **kwargs)
    monkeypatch.setattr(ppo, "ppo_update", update_then_signal)
    result = ppo.train(_tiny_config(clip_dir, tmp_path, num_envs=2, frames=10**6, checkpoint_every=100))
    rows = _progress_rows(tmp_path / "progress.csv")
    # iteration 1 only initialises the observation statistics: the third update is iteration 4's
    assert result.interrupted and result.iteration == 4
    assert load_checkpoint(tmp_path)["iteration"] == int(rows[-1]["iteration"]) == 4


def test_a_second_stop_signal_stops_at_once() -> None:
    import os
    import signal

    from crisp_gym.train.ppo import StopSignals

    reached, before = [], signal.getsignal(signal.SIGTERM)
    with StopSignals() as stop, pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        with stop.deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            reached.append("after the first")
            os.kill(os.getpid(), signal.SIGTERM)
            reached.append("after the second")
    assert reached == ["after the first"]
    assert signal.getsignal(signal.SIGTERM) is before


def test_resume_keeps_the_adaptive_start_samplers_failure_counts(clip_dir: Path, tmp_path: Path) -> None:
    from crisp_gym.policy.files import load_checkpoint
    from crisp_gym.train.ppo import train

    cfg = _tiny_config(clip_dir, tmp_path, num_envs=4, frames=4 * 128, start_sampling="adaptive")
    train(cfg)
    saved = load_checkpoint(tmp_path)["start_failures"]
    assert sum(float(f.sum()) for f in saved) > 0  # the untrained policy fails somewhere
    train(replace(cfg, resume=True))  # nothing left to train: the restored counts are saved again
    for before, after in zip(saved, load_checkpoint(tmp_path)["start_failures"]):
        torch.testing.assert_close(after, before, rtol=0, atol=0)


def test_the_best_evaluated_weights_are_kept(clip_dir: Path, tmp_path: Path, monkeypatch) -> None:
    """``best.pt`` holds the weights of the best evaluation (RSI success + share tracked from
    frame 0), not the last one; a resumed run only replaces it with a better one."""
    from crisp_gym.policy.files import load_checkpoint
    from crisp_gym.train import rollouts
    from crisp_gym.train.ppo import train

    scores = iter([(0.5, 20), (0.9, 89), (0.2, 10), (0.8, 80), (0.95, 89)])

    def scripted(self, policy):
        success, frames = next(scores)
        return {name: {"success": success, "frames": frames, "num_frames": 90, "whole_clip": frames == 89}
                for name in self.names}
    monkeypatch.setattr(rollouts.LibraryEvaluation, "__call__", scripted)
    cfg = _tiny_config(clip_dir, tmp_path, num_envs=4, frames=3 * 128, eval_every=1, eval_episodes=2)
    train(cfg)
    best = load_checkpoint(tmp_path / "best.pt")
    assert best["iteration"] == 2 and best["evaluation_score"] == pytest.approx(0.9 + 89 / 90)
    train(replace(cfg, frames=4 * 128, resume=True))  # (0.8, 80) is worse: kept
    assert load_checkpoint(tmp_path / "best.pt")["iteration"] == 2
    train(replace(cfg, frames=5 * 128, resume=True))  # (0.95, 89) is better: replaced
    assert load_checkpoint(tmp_path / "best.pt")["iteration"] == 5


@pytest.mark.parametrize("field", ["actor_lr", "critic_lr", "clip_epsilon", "max_grad_norm"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), 0.0, -1e-4])
def test_rates_that_no_optimiser_can_use_are_refused_by_the_config(clip_dir: Path, field: str, value: float) -> None:
    """``--actor-lr nan`` was accepted until the first update failed with "actions must be finite"."""
    from crisp_gym.train.config import TrainConfig

    with pytest.raises(ValueError, match=f"{field}=.*must be positive and finite"):
        TrainConfig(clip=str(clip_dir), **{field: value})


def test_files_that_are_not_runs_get_a_one_line_error(tmp_path: Path) -> None:
    """A random ``.pt`` to eval gave "pop from empty list"; a resume without a checkpoint a bare
    FileNotFoundError traceback. Each now names the file and what it is not."""
    from crisp_gym.policy.files import load_checkpoint
    from crisp_gym.train.checkpoints import load_policy

    torch.save({"weights": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="other.pt is neither a crisp-gym training checkpoint nor a policy file"):
        load_policy(tmp_path / "other.pt")
    (tmp_path / "garbage.pt").write_bytes(b"\x00\x01" * 100)
    with pytest.raises(ValueError, match="garbage.pt is not a .*torch file"):
        load_policy(tmp_path / "garbage.pt")
    with pytest.raises(FileNotFoundError, match=f"no checkpoint at {tmp_path / 'run' / 'checkpoint.pt'}"):
        load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    with pytest.raises(ValueError, match="other.pt is not a version-.* crisp-gym training checkpoint"):
        load_checkpoint(tmp_path / "other.pt")


def test_training_scalars_reach_torchrl_loggers(clip_dir: Path, tmp_path: Path) -> None:
    """``--loggers csv tensorboard``: TorchRL's CSV logger and TensorBoard's event file get the
    scalars of ``progress.csv``, at the same frame counts (read back with each tool's own reader)."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from crisp_gym.train.ppo import train

    cfg = _tiny_config(clip_dir, tmp_path / "run", frames=2048, loggers=("csv", "tensorboard"))
    train(cfg)
    rows = _progress_rows(tmp_path / "run" / "progress.csv")
    expected = [(int(r["frames"]), float(r["mean_return"])) for r in rows if r["mean_return"] not in ("", "nan")]
    assert expected
    (csv_file,) = (tmp_path / "run" / "trackers").rglob("mean_return.csv")
    with open(csv_file, newline="") as f:
        logged = [(int(step), float(value)) for step, value in csv.reader(f)]
    assert logged == pytest.approx(expected)
    (events,) = {p.parent for p in (tmp_path / "run" / "trackers").rglob("events.out.tfevents.*")}
    accumulator = EventAccumulator(str(events))
    accumulator.Reload()
    board = [(e.step, e.value) for e in accumulator.Scalars("mean_return")]
    assert board == pytest.approx(expected, rel=1e-6)  # event files store float32


def test_an_unknown_logger_is_named() -> None:
    from crisp_gym.train.config import TrainConfig

    with pytest.raises(ValueError, match=r"unknown loggers \['neptune'\]; TorchRL's are csv, tensorboard"):
        TrainConfig(loggers=("neptune",))


def test_collection_on_two_ray_workers_trains_with_their_frames(clip_dir: Path, tmp_path: Path) -> None:
    """``--ray-workers 2``: TorchRL's RayCollector on a local Ray cluster of two workers, each with
    its own batched env; an iteration has both workers' frames, the losses are finite, and the
    checkpoint resumes like any other."""
    pytest.importorskip("ray")
    from crisp_gym.policy.files import load_checkpoint
    from crisp_gym.train.ppo import train

    cfg = _tiny_config(clip_dir, tmp_path / "run", frames=4 * 2 * 16 * 8, num_envs=16, steps_per_env=8,
                       minibatch_size=64, ray_workers=2)
    result = train(cfg)
    assert result.iteration == 4 and result.frames == 4 * 2 * 16 * 8
    rows = _progress_rows(tmp_path / "run" / "progress.csv")
    assert all(int(b["frames"]) - int(a["frames"]) == 2 * 16 * 8 for a, b in zip(rows, rows[1:]))
    assert all(np.isfinite(float(r["loss_critic"])) for r in rows[1:])
    assert load_checkpoint(tmp_path / "run")["frames"] == result.frames


def test_shared_start_counts_sum_the_workers_and_share_a_restored_total(tmp_path: Path) -> None:
    from crisp_gym.envs.config import TrackConfig
    from crisp_gym.envs.start_sampler import StartSampler
    from crisp_gym.train.workers import SharedStartCounts, counts_table

    sampler = StartSampler([61, 31], TrackConfig(start_sampling="adaptive", adaptive_bin_seconds=1.0))
    with SharedStartCounts(sampler, workers=2) as counts:
        seen = [StartSampler([61, 31], sampler.config) for _ in counts.paths]  # as each worker's env does
        for worker, path in zip(seen, counts.paths):
            worker.attach(counts_table(path, worker.counts_size))
        seen[0].record(np.array([0, 1]), np.array([40, 5]), np.array([True, True]))
        seen[1].record(np.array([0]), np.array([10]), np.array([True]))
        counts.gather()
        for kept, a, b in zip(sampler.failures, *(w.failures for w in seen)):
            np.testing.assert_array_equal(kept, a + b)
        np.testing.assert_array_equal(sampler.ended, seen[0].ended + seen[1].ended)
        sampler.failures[0][:] = [4.0, 6.0]  # a resumed run's counts
        counts.scatter()
        assert [w.failures[0].tolist() for w in seen] == [[2.0, 3.0], [2.0, 3.0]]
        directory = counts.paths[0].parent
    assert not directory.exists()


def test_collection_in_two_worker_processes(clip_dir: Path, tmp_path: Path) -> None:
    """``collector_workers=2``: TorchRL's MultiSyncCollector, the simulations split between two
    spawned processes. An iteration has the configured frames, the adaptive start counts reach
    the log and the checkpoint, the same seed gives the same run, and it resumes."""
    from crisp_gym.policy.files import load_checkpoint
    from crisp_gym.train.ppo import train

    cfg = _tiny_config(clip_dir, tmp_path / "a", frames=5 * 4 * 16, num_envs=4, steps_per_env=16, minibatch_size=32,
                       epochs=1, start_sampling="adaptive", collector_workers=2)
    runs = [train(cfg), train(replace(cfg, output=tmp_path / "b"))]
    assert [(r.iteration, r.frames) for r in runs] == [(5, 5 * 4 * 16)] * 2
    logs = [_progress_rows(tmp_path / name / "progress.csv") for name in "ab"]
    for column in ("loss_objective", "loss_critic", "episodes", "mean_return", "start_failures/walk"):
        assert [r[column] for r in logs[0]] == [r[column] for r in logs[1]], column
    assert float(logs[0][-1]["start_failures/walk"]) > 0  # the untrained policy fails somewhere
    saved = load_checkpoint(tmp_path / "a")["start_failures"]
    assert float(saved[0].sum()) == pytest.approx(float(logs[0][-1]["start_failures/walk"]))
    resumed = train(replace(cfg, frames=7 * 4 * 16, resume=True))
    assert (resumed.iteration, resumed.frames) == (7, 7 * 4 * 16)
    assert all(np.isfinite(float(r["loss_critic"])) for r in _progress_rows(tmp_path / "a" / "progress.csv")[1:])


def test_collector_workers_must_split_the_simulations_and_give_way_to_ray() -> None:
    from crisp_gym.train.config import TrainConfig, cpu_profile

    with pytest.raises(ValueError, match=r"divide num_envs \(5\), got 2"):
        TrainConfig(num_envs=5, collector_workers=2)
    assert TrainConfig(num_envs=6, collector_workers=3).worker_processes == 3
    assert cpu_profile(ray_workers=4).worker_processes == 0  # Ray collects: the profile's local workers do not apply


def _session_processes(session: int, marker: str) -> list[int]:
    """Pids of the processes of ``session`` whose command line contains ``marker``."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes().decode(errors="replace")
        except OSError:  # the process ended meanwhile
            continue
        if int(fields[3]) == session and marker in cmdline:
            pids.append(int(stat.parent.name))
    return pids


def test_a_terminals_interrupt_while_workers_start_stops_the_run(clip_dir: Path, tmp_path: Path) -> None:
    """Ctrl-C in a terminal (SIGINT to the whole process group) while the spawned workers are
    still importing, before they can ignore it: the run stops with its checkpoint, exit code 130,
    and no worker is left. A worker killed there left the trainer waiting for it forever."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "run"
    command = [sys.executable, "-m", "crisp_gym.train.cli", "--profile", "cpu", "--clip", str(clip_dir), "-o", str(out),
               "--num-envs", "4", "--steps-per-env", "4", "--collector-workers", "2", "--no-progress",
               "--model.mlp-actor-hidden", "32", "--model.critic-hidden", "32"]
    # a terminal's foreground job: SIGINT at its default, in a process group of its own
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        while not _session_processes(process.pid, "spawn_main") and time.monotonic() < deadline:
            assert process.poll() is None, process.stderr.read().decode()[-2000:]
            time.sleep(0.02)
        assert _session_processes(process.pid, "spawn_main"), "no worker started"
        os.killpg(process.pid, signal.SIGINT)
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode == 130, stderr.decode()[-2000:]
    assert (out / "checkpoint.pt").is_file()
    assert not _session_processes(process.pid, "spawn_main")


def test_collector_workers_outlive_a_terminals_interrupt(clip_dir: Path) -> None:
    """A terminal's Ctrl-C sends SIGINT to every process of the group: the workers ignore it (and
    SIGTERM), and keep collecting until the trainer, which saves its checkpoint first, stops them.
    A worker that died of it left the trainer waiting for its reply forever."""
    import os
    import signal
    import time

    from crisp_gym.train.ppo import build_agent, make_env
    from crisp_gym.train.workers import SharedStartCounts, worker_collector, worker_config

    cfg = _tiny_config(clip_dir, Path("unused"), num_envs=4, steps_per_env=4, collector_workers=2)
    env = make_env(worker_config(cfg), 0)
    agent = build_agent(cfg.model, env.observation_spec["targets"].shape[-2], 0)
    with SharedStartCounts(env.vec_env.start_sampler, 2) as counts:
        collector = worker_collector(cfg, make_env, agent.policy, counts, seed=1)
        try:
            batches = iter(collector)
            assert next(batches).shape == (2, 2, 4)
            for process in collector.procs:
                os.kill(process.pid, signal.SIGINT)
                os.kill(process.pid, signal.SIGTERM)
            time.sleep(1.0)
            assert all(process.is_alive() for process in collector.procs)
            # the workers act with the trainer's current weights and observation statistics (as after an update)
            with torch.no_grad():
                agent.actor.actor.action_head.bias += 0.05
            agent.normalizer.update(*_obs((64,), scene_aware=False, seed=5)[:2])
            collector.update_policy_weights_()
            batch = next(batches)
            assert batch.shape == (2, 2, 4)
            with torch.no_grad():
                loc, _ = agent.actor(batch["proprio"], batch["targets"])
            torch.testing.assert_close(batch["loc"], loc, rtol=1e-5, atol=1e-6)
        finally:
            collector.shutdown()
