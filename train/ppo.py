"""PPO for ``CrispTrack-v0``, written to be read top to bottom (in the spirit of single-file PPOs).

Pieces, all from TorchRL except the env adapter:

* env: :class:`~train.env.CrispTrackTorchEnv` around the batched ``CrispTrack-v0``;
* collection: ``torchrl.collectors.Collector`` (``num_envs × steps_per_env`` frames per
  iteration, trajectories continue across iterations);
* advantages: ``torchrl.objectives.value.GAE`` (γ = 0.99, λ = 0.95) on values from
  :func:`estimate_values` (one critic pass per batch instead of GAE's two), normalised per
  minibatch by :func:`normalize_advantages`;
* loss: ``torchrl.objectives.ClipPPOLoss`` (no entropy bonus: σ is fixed);
* optimiser: one Adam with two parameter groups (actor lr 2e-5 as in the paper; critic lr
  1e-4, our choice: the paper gives a single rate, and the critic's regression targets move
  much faster than the policy should).

Each iteration: collect → GAE → ``epochs`` passes of shuffled minibatches → update the
observation normaliser from the batch (after the update, so the minibatches see the
statistics the behaviour policy used) → log → every ``checkpoint_every`` iterations an atomic
checkpoint (temp file, then rename). ``resume=True`` continues from the output directory's
checkpoint (weights, normaliser, optimiser, iteration and frame counts).

Outputs in ``output``: ``config.json``, ``checkpoint.pt``, ``progress.csv`` and, with
``loggers``, the same scalars through TorchRL's experiment loggers (``torchrl.record.loggers``:
CSV, TensorBoard, W&B, MLflow) under ``output/trackers``.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import torch
import tyro
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from tqdm.auto import tqdm

from crisp_gym.atomic import atomic_path, write_text
from crisp_gym.file_errors import reading
from crisp_gym.torch_file import load_tensors
from train.models import PROPRIO_DIM, TARGET_DIM, Critic, FixedStdGaussian, ModelConfig, ObsNormalizer, build_actor

CHECKPOINT_NAME = "checkpoint.pt"
BEST_NAME = "best.pt"  # the checkpoint of the best periodic evaluation so far
CHECKPOINT_FORMAT = 1
POLICY_NAME = "policy.pt"
POLICY_FORMAT = 1
LOGGERS = ("csv", "tensorboard", "wandb", "mlflow")
"""The experiment loggers of ``torchrl.record.loggers`` that ``TrainConfig.loggers`` may name."""
_CSV_FIELDS = ("iteration", "frames", "time_s", "fps", "episodes", "mean_return", "mean_length", "success_rate",
               "loss_objective", "loss_critic", "kl_approx", "clip_fraction", "explained_variance",
               "collect_s", "env_s", "update_s")


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs; defaults are the paper's values where it gives them.

    Attributes:
        clip: clips to train on: names (registry), registry tags (``bundled``: every bundled
            clip) or clip directories; several make a motion library.
        clip_weights: relative probability of each clip at a reset (``None``: equal).
        start_sampling: ``"uniform"`` reference state init or ``"adaptive"`` (starts drawn
            where episodes recently failed; :mod:`crisp_gym.envs.start_sampler`).
        output: run directory (config, checkpoint, CSV log).
        scene_aware: train the scene-aware policy (``points`` observation, PointNet tokens).
        velocity_feedforward: PD targets lead the reference by the servos' kd/kp times its hinge
            velocities, so fast moves are not lagged by the servos' damping (the env option of
            the same name).
        frames: total environment steps (the paper does not state its budget).
        num_envs: parallel simulations (paper: 2048).
        steps_per_env: steps collected per simulation and iteration (horizon of the GAE
            segments; frames per iteration = ``num_envs × steps_per_env``).
        minibatch_size: samples per gradient step (paper: 8192).
        epochs: passes over each iteration's batch.
        gamma: discount (paper: 0.99).
        gae_lambda: GAE λ (paper: τ = 0.95).
        clip_epsilon: PPO ratio clip.
        actor_lr: actor learning rate (paper: 2e-5).
        critic_lr: critic learning rate (not in the paper; see the module docstring).
        max_grad_norm: gradient-norm clip, applied to actor and critic separately.
        critic_loss: ``"l2"`` or ``"smooth_l1"``.
        normalize_advantage: normalise advantages per minibatch (zero mean, unit std).
        normalize_obs: running observation normalisation (proprio and targets).
        reward_scale: factor on the rewards PPO learns from (not the logged returns); see
            :class:`~train.env.TrainingReward`.
        energy_cap: bound on the energy penalty's magnitude per step in the rewards PPO
            learns from (``None``: unbounded, as in the paper); see
            :class:`~train.env.TrainingReward`.
        model: actor/critic architecture (paper: transformer actor, [1024, 512] critic).
        seed: seeds torch, the minibatch shuffles and the env's start frames.
        device: ``"auto"`` (CUDA when available), ``"cpu"``, ``"cuda"``...
        num_threads: MuJoCo threads stepping the batch (0: all CPUs).
        torch_threads: torch intra-op threads (0: torch's default).
        checkpoint_every: iterations between checkpoints (one is also written at the end).
        eval_every: iterations between deterministic evaluations (the policy's mean action, per
            clip: success from ``eval_episodes`` fixed RSI starts and frames tracked from frame
            0), logged in ``progress.csv`` and ``evaluation.png``; 0 disables them.
        eval_episodes: RSI episodes per clip in each evaluation (plus one from frame 0).
        until_success: stop once an evaluation finds every clip at this RSI success or more,
            and tracked from frame 0 to the end (``None``: train for ``frames``).
        init_from: warm start: a policy file, run directory or checkpoint whose actor (and,
            from a checkpoint, critic) weights and observation statistics start this run. Its
            architecture must match this run's.
        critic_warmup: with ``init_from`` and no critic in it, iterations that train only the
            critic, so a random critic's advantages do not undo the loaded actor.
        init_stats_samples: with ``init_from``, the loaded observation statistics count as at
            most this many samples (``None``: as many as built them), so that the new clips'
            observations move them. The library's statistics come from synthetic clips whose
            arms barely move: a captured person's arm swing normalises to the ±5σ clip on dozens
            of features, and after 19.7 M samples new data barely shifts them.
        actor_lr_warmup: with ``init_from``, iterations over which the actor's learning rate
            rises linearly from 0 once it starts training. Adam's first steps move every
            weight by the full learning rate whatever the gradient's size: from a trained
            actor the first update was measured at KL 0.15 with half the samples clipped
            (0.01–0.02 later), and a 97 %-success policy fell to 44 % within 0.5 M frames.
        resume: continue from ``output/checkpoint.pt``.
        progress: show a progress bar.
        ray_workers: collect on this many Ray workers, each with its own batched env of
            ``num_envs`` simulations (an iteration then has ``ray_workers`` times the frames);
            0: in this process. Each worker's env keeps its own adaptive start sampler, so
            ``start_failures/*`` in ``progress.csv`` and the checkpoint stay empty.
        ray_address: a Ray cluster to collect on (``auto``, ``ray://HEAD:10001``); default: a local
            one of ``ray_workers`` cores.
        loggers: experiment trackers that also get every ``progress.csv`` scalar (step: frames),
            through ``torchrl.record.loggers``: ``csv``, ``tensorboard``, ``wandb``, ``mlflow``
            (the last three need their package: ``pip install 'crisp-gym[tracking]'`` has
            TensorBoard and W&B).
    """

    clip: tuple[str, ...] = ("flat_walk",)
    clip_weights: tuple[float, ...] | None = None
    start_sampling: str = "uniform"
    output: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("runs/track")
    scene_aware: bool = False
    velocity_feedforward: bool = False
    frames: int = 1_000_000_000
    num_envs: int = 2048
    steps_per_env: int = 32
    minibatch_size: int = 8192
    epochs: int = 5
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_epsilon: float = 0.2
    actor_lr: float = 2e-5
    critic_lr: float = 1e-4
    max_grad_norm: float = 1.0
    critic_loss: str = "l2"
    normalize_advantage: bool = True
    normalize_obs: bool = True
    reward_scale: float = 1.0
    energy_cap: float | None = None
    model: ModelConfig = field(default_factory=ModelConfig)
    seed: int = 0
    device: str = "auto"
    num_threads: int = 0
    torch_threads: int = 0
    checkpoint_every: int = 20
    eval_every: int = 0
    eval_episodes: int = 32
    until_success: float | None = None
    init_from: Path | None = None
    init_stats_samples: int | None = None
    critic_warmup: int = 20
    actor_lr_warmup: int = 100
    resume: bool = False
    progress: bool = True
    loggers: tuple[str, ...] = ()
    ray_workers: int = 0
    ray_address: str | None = None

    def __post_init__(self) -> None:
        if isinstance(self.clip, (str, os.PathLike)):  # one clip, as configs before motion libraries held it
            object.__setattr__(self, "clip", (str(self.clip),))
        if not self.clip:
            raise ValueError("clip must name at least one clip")
        positive = ("num_envs", "steps_per_env", "minibatch_size", "epochs", "checkpoint_every", "eval_episodes")
        bad = [name for name in positive if getattr(self, name) < 1]
        if bad:
            raise ValueError(f"{', '.join(bad)} must be at least 1")
        if self.frames < 0:
            raise ValueError(f"frames must be non-negative, got {self.frames}")
        if not (0 < self.gamma <= 1 and 0 <= self.gae_lambda <= 1):
            raise ValueError("gamma must be in (0, 1] and gae_lambda in [0, 1]")
        if self.critic_loss not in ("l2", "smooth_l1"):
            raise ValueError(f"critic_loss must be 'l2' or 'smooth_l1', got {self.critic_loss!r}")
        if self.init_stats_samples is not None and self.init_stats_samples < 1:
            raise ValueError(f"init_stats_samples must be at least 1, got {self.init_stats_samples}")
        if self.eval_every < 0 or self.critic_warmup < 0 or self.actor_lr_warmup < 0:
            raise ValueError("eval_every, critic_warmup and actor_lr_warmup must be non-negative")
        if self.until_success is not None and not (0 < self.until_success <= 1 and self.eval_every > 0):
            raise ValueError("until_success must be in (0, 1] and needs eval_every > 0")
        if self.ray_workers < 0 or (self.ray_address is not None and not self.ray_workers):
            raise ValueError("ray_workers must be at least 0, and ray_address needs ray_workers > 0")
        unknown = [name for name in self.loggers if name not in LOGGERS]
        if unknown:
            raise ValueError(f"unknown loggers {unknown}; TorchRL's are {', '.join(LOGGERS)}")
        rates = {name: getattr(self, name) for name in ("actor_lr", "critic_lr", "clip_epsilon", "max_grad_norm")}
        bad_rates = [f"{name}={value!r}" for name, value in rates.items() if not (math.isfinite(value) and value > 0)]
        if bad_rates:
            raise ValueError(f"{', '.join(bad_rates)}: must be positive and finite")

    @property
    def frames_per_iteration(self) -> int:
        return self.num_envs * self.steps_per_env


def paper_profile(**overrides: Any) -> TrainConfig:
    """The paper's setup (transformer actor, 2048 envs, batch 8192, lr 2e-5): for a GPU machine."""
    return replace(TrainConfig(), **overrides)


def cpu_profile(**overrides: Any) -> TrainConfig:
    """A setup for a small CPU machine (aimed at 2 cores), where the PPO update, not physics, is the cost.

    Differences from the paper's profile and why (measured on ``flat_walk`` on 2 cores; the
    runs, and the shipped policy that one run of exactly this profile trained in 41 min, are
    described in ``docs/training.md``):

    * small MLPs: actor (256, 256), critic (256, 256). Both read the 2,521 observation
      features, so their first layers are most of the update's cost; the update is
      compute-bound (~100 GFLOP/s per thread measured), and these cost about a quarter of a
      (512, 512) actor with the paper's (1024, 512) critic. A (512, 256) critic learned no
      better and trained 12–15 % slower. The policy file stays under 3 MB;
    * 64 envs × 16 steps = 1,024 frames per iteration, 2 epochs of 512-sample minibatches.
      With σ = 0.055 over 69 dimensions, moving the mean by 0.004 rad already costs a KL of
      ~0.15, so PPO's clip rather than the learning rate bounds each iteration's step, and a
      frame budget goes further in more, smaller iterations: 4 epochs over 4,096 frames
      clipped 50–60 % of the samples at KL 0.10–0.20; 2 epochs over 1,024 frames clip
      ~16 % at KL ~0.02 with actor lr 3e-5, at half the update cost per frame;
    * actor lr 3e-5 (paper 2e-5, but 4 gradient steps per 1,024 frames instead of 40 per
      65,536). The previous profile (2e-5, 2 steps per 8,192 frames) left KL at ~0.001 and the
      clip fraction at ~0.003: the return stayed flat over 130 K frames. 1e-4 clipped 42–46 %;
      from the same state, 300 K frames later its mean return was 15 % below 3e-5's. Critic
      lr 5e-4;
    * the rewards PPO learns from are scaled by 0.05 (values of O(1–10) instead of O(100) for
      the critic) and the energy penalty is capped at 2 per step. Unbounded, it reaches
      −2…−5 per step in a fall, more than all tracking terms together, and ending the
      episode early starts to pay. A cap of 0.5 was too low: the policy learned to survive
      longer while spending −0.6…−0.8 per step, where the capped penalty gives no gradient.
      Logged returns and evaluations use the env's own reward;
    * collection runs one torch thread (each step's 64-sample forward pass is too small to
      split, and a second thread competes with MuJoCo's); the update uses torch's default
      (all cores): on 2 idle cores that made it 1.36× faster end to end. On a machine shared
      with other jobs one thread can be faster (``--torch-threads 1``);
    * a smaller PointNet (per-point widths 32, 64 instead of 64, 128, 256): with 128 points
      per sample the paper-sized one made the scene-aware update ~3× slower than the
      scene-blind one;
    * a 20 M frame budget;
    * adaptive start sampling (starts drawn where episodes recently failed, 20 % uniform):
      a clip's hard part (standing up from a seat, a stair landing) is a small share of its
      frames, and uniform starts spend most of the budget on what the policy already tracks;
    * a deterministic evaluation of every clip every 500 iterations (~0.5 M frames; 32 RSI
      starts and frame 0 per clip), which ``--until-success`` reads.

    Residual actions (the env's default) are kept: an untrained policy already tracks the
    reference pose with its PD targets, which matters most when few frames are affordable.
    """
    base = TrainConfig(num_envs=64, steps_per_env=16, minibatch_size=512, epochs=2, actor_lr=3e-5,
                       critic_lr=5e-4, reward_scale=0.05, energy_cap=2.0, frames=20_000_000, checkpoint_every=20,
                       start_sampling="adaptive", eval_every=500, eval_episodes=32,
                       model=ModelConfig(actor="mlp", mlp_actor_hidden=(256, 256), critic_hidden=(256, 256),
                                         pointnet_hidden=(32, 64)))
    return replace(base, **overrides)


# --------------------------------------------------------------------------------------------
# Building blocks


@dataclass
class Agent:
    """The networks of a run and their TorchRL wrappers.

    Attributes:
        actor: (loc, scale) of the Gaussian policy from the observation tensors.
        critic: state value from the observation tensors.
        normalizer: the observation normaliser shared by ``actor`` and ``critic``.
        policy: TorchRL probabilistic actor (samples ``action``, writes its log-prob).
        value: TorchRL value operator (writes ``state_value``).
    """

    actor: FixedStdGaussian
    critic: Critic
    normalizer: ObsNormalizer
    policy: Any
    value: Any


def obs_keys(scene_aware: bool) -> list[str]:
    return ["proprio", "targets", "points"] if scene_aware else ["proprio", "targets"]


def build_agent(model: ModelConfig, num_targets: int, num_points: int, normalize_obs: bool = True,
                device: torch.device | str = "cpu") -> Agent:
    """Actor, critic and their TorchRL wrappers; ``num_points`` 0 means scene-blind."""
    from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator

    scene_aware = num_points > 0
    normalizer = ObsNormalizer(num_targets, clip=model.obs_clip, enabled=normalize_obs)
    actor = FixedStdGaussian(build_actor(model, num_targets, scene_aware, normalizer), model.action_std)
    critic = Critic(num_targets, num_points, normalizer, model.critic_hidden)
    actor.to(device)
    critic.to(device)
    keys = obs_keys(scene_aware)
    policy = ProbabilisticActor(TensorDictModule(actor, in_keys=keys, out_keys=["loc", "scale"]),
                                in_keys=["loc", "scale"], distribution_class=IndependentNormal,
                                distribution_kwargs={"tanh_loc": False}, return_log_prob=True)
    value = ValueOperator(critic, in_keys=keys)
    return Agent(actor, critic, normalizer, policy, value)


def make_env(cfg: TrainConfig, seed: int | None = None):
    """The batched ``CrispTrack-v0`` for ``cfg`` behind the TorchRL adapter."""
    import gymnasium as gym

    import crisp_gym  # noqa: F401  (registers CrispTrack-v0)
    from train.env import CrispTrackTorchEnv, TrainingReward

    vec_env = gym.make_vec("CrispTrack-v0", num_envs=cfg.num_envs, vectorization_mode="vector_entry_point",
                           clip=list(cfg.clip), scene_aware=cfg.scene_aware, num_threads=cfg.num_threads,
                           clip_weights=cfg.clip_weights, start_sampling=cfg.start_sampling,
                           velocity_feedforward=cfg.velocity_feedforward)
    return CrispTrackTorchEnv(vec_env, seed=seed, reward=TrainingReward(cfg.reward_scale, cfg.energy_cap))


def normalize_advantages(advantage: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Zero-mean, unit-std advantages (population std; a single sample becomes 0)."""
    if advantage.numel() < 2:
        return advantage - advantage.mean()
    return (advantage - advantage.mean()) / (advantage.std(unbiased=False) + eps)


def estimate_values(data: TensorDictBase, value: Any) -> None:
    """Write ``state_value`` and ``("next", "state_value")`` into a ``(num_envs, T)`` batch.

    A step's next observation is the following step's observation except where an episode
    ended (the env reset in between) and at the batch's last step, so the critic runs on all
    observations plus only those next observations: about half the work of TorchRL's GAE,
    which evaluates it on both in full. The values are the same.
    """
    value(data)
    current = data["state_value"]
    following = torch.empty_like(current)
    following[:, :-1] = current[:, 1:]
    fresh = data["next", "done"].reshape(current.shape[:2]).clone()
    fresh[:, -1] = True
    rows, steps = fresh.nonzero(as_tuple=True)
    ends = value(data["next"][rows, steps].select(*value.in_keys))
    following[rows, steps] = ends["state_value"]
    data.set(("next", "state_value"), following)


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


# --------------------------------------------------------------------------------------------
# Checkpoints


def _config_dict(cfg: TrainConfig) -> dict[str, Any]:
    data = asdict(cfg)
    data["output"] = str(cfg.output)
    data["clip"] = list(cfg.clip)
    data["init_from"] = None if cfg.init_from is None else str(cfg.init_from)
    return data


def config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """Inverse of the ``config`` entry of a checkpoint (unknown keys are an error)."""
    data = dict(data)
    model = ModelConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.pop("model").items()})
    for key in ("clip", "clip_weights"):  # JSON keeps tuples as lists
        if isinstance(data.get(key), list):
            data[key] = tuple(data[key])
    if data.get("init_from") is not None:
        data["init_from"] = Path(data["init_from"])
    return TrainConfig(**{**data, "output": Path(data["output"]), "model": model})


def save_checkpoint(path: str | Path, agent: Agent, optimizer: torch.optim.Optimizer, iteration: int,
                    frames: int, cfg: TrainConfig, generator: torch.Generator,
                    start_failures: list[np.ndarray] | None = None, evaluation_score: float | None = None) -> Path:
    """Write a checkpoint atomically (a temporary file, synced, then renamed over ``path``).

    ``start_failures``: the adaptive start sampler's failure counts per clip, so a resumed run
    starts where the interrupted one was failing. ``evaluation_score``: the
    :func:`evaluation_score` of the weights, for the best-evaluated checkpoint.
    """
    path = Path(path)
    state = {
        "format_version": CHECKPOINT_FORMAT,
        "iteration": iteration,
        "frames": frames,
        "config": _config_dict(cfg),
        "actor": agent.actor.state_dict(),
        "critic": agent.critic.state_dict(),
        "optimizer": optimizer.state_dict(),
        "generator": generator.get_state(),
        "torch_rng": torch.get_rng_state(),
    }
    if evaluation_score is not None:
        state["evaluation_score"] = float(evaluation_score)
    if start_failures is not None:
        state["start_failures"] = [torch.from_numpy(np.asarray(f, dtype=np.float64)) for f in start_failures]
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(state, f)
        f.flush()
        os.fsync(f.fileno())
    return path


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """A checkpoint's contents (tensors and plain Python values only)."""
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    state = load_tensors(path)
    if not isinstance(state, dict) or state.get("format_version") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a version-{CHECKPOINT_FORMAT} crisp-gym training checkpoint")
    return state


def load_policy(path: str | Path, device: torch.device | str = "cpu") -> tuple[FixedStdGaussian, TrainConfig]:
    """The trained actor ((loc, scale) from observations, normaliser included) and its config.

    ``path`` is a run directory (its ``policy.pt`` if it has one, else its ``checkpoint.pt``),
    a training checkpoint or a policy file written by :func:`export_policy`.
    """
    path, state = _read_policy_source(path)
    try:
        with reading(path, "policy"):
            return _build_policy(state, device)
    except RuntimeError as err:  # torch: weights whose shapes disagree with the configured model
        raise ValueError(f"{path}: a damaged or inconsistent policy ({err})") from err


def _build_policy(state: dict[str, Any], device: torch.device | str) -> tuple[FixedStdGaussian, TrainConfig]:
    cfg = config_from_dict(state["config"])
    if state.get("kind") == "policy":
        num_targets = state["actor"]["actor.normalizer.targets.mean"].shape[0]
        normalizer = ObsNormalizer(num_targets, clip=cfg.model.obs_clip, enabled=cfg.normalize_obs)
        actor = FixedStdGaussian(build_actor(cfg.model, num_targets, cfg.scene_aware, normalizer),
                                 cfg.model.action_std)
        actor.load_state_dict(state["actor"])
        return actor.to(device).eval(), cfg
    num_targets, num_points = _obs_sizes(state["critic"])
    agent = build_agent(cfg.model, num_targets, num_points if cfg.scene_aware else 0, cfg.normalize_obs, device)
    agent.actor.load_state_dict(state["actor"])
    agent.critic.load_state_dict(state["critic"])
    return agent.actor.eval(), cfg


def _read_policy_source(path: str | Path) -> tuple[Path, dict[str, Any]]:
    """(file, contents) of a run directory, checkpoint or policy file."""
    path = Path(path)
    if path.is_dir():
        path = path / POLICY_NAME if (path / POLICY_NAME).is_file() else path / CHECKPOINT_NAME
    if not path.is_file():
        raise FileNotFoundError(f"no policy at {path}: expected a run directory, a {CHECKPOINT_NAME} "
                                f"or a {POLICY_NAME}")
    state = load_tensors(path)
    if not isinstance(state, dict) or not (
            state.get("kind") == "policy" and state.get("format_version") == POLICY_FORMAT
            or state.get("format_version") == CHECKPOINT_FORMAT and "critic" in state):
        raise ValueError(f"{path} is neither a crisp-gym training checkpoint nor a policy file "
                         f"(version {CHECKPOINT_FORMAT}/{POLICY_FORMAT})")
    return path, state


def export_policy(run: str | Path, output: str | Path, clip: str | tuple[str, ...] | None = None,
                  with_critic: bool = False) -> Path:
    """Write a run's actor as a small self-contained policy file, ``output/policy.pt``.

    It holds the actor's ``state_dict`` (observation-normaliser statistics included), the
    run's config and its training totals (iterations, frames, wall time from
    ``progress.csv``): all :func:`load_policy` needs, without the critic and optimiser state
    that make a checkpoint several times larger.

    Args:
        run: run directory or checkpoint file.
        output: directory for ``policy.pt`` (created).
        clip: clip name(s) to record in the config instead of the run's (e.g. registered names
            in place of machine-specific directories).
        with_critic: keep the critic too (a training milestone: ``crisp train --init-from``
            then continues with both networks warm; the optimiser state is never kept).
    """
    checkpoint = Path(run) / CHECKPOINT_NAME if Path(run).is_dir() else Path(run)
    state = load_checkpoint(checkpoint)
    config = dict(state["config"])
    if clip is not None:
        config["clip"] = [clip] if isinstance(clip, str) else list(clip)
    payload = {
        "format_version": POLICY_FORMAT,
        "kind": "policy",
        "config": config,
        "actor": state["actor"],
        "training": policy_training_stats(checkpoint),
    }
    if with_critic:
        payload["critic"] = state["critic"]
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    path = output / POLICY_NAME
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def policy_training_stats(path: str | Path) -> dict[str, float | None]:
    """Training totals of a run directory, checkpoint or policy file: iterations, frames and
    wall time (``None`` when the run's ``progress.csv`` is not next to its checkpoint)."""
    path, state = _read_policy_source(path)
    if state.get("kind") == "policy":
        return dict(state["training"])
    return {"iterations": state["iteration"], "frames": state["frames"],
            "wall_time_s": run_wall_time(path.parent / "progress.csv")}


def run_wall_time(progress_csv: str | Path) -> float | None:
    """Seconds a run trained in total, from its ``progress.csv`` (resumed segments added up);
    ``None`` without the file."""
    path = Path(progress_csv)
    if not path.is_file():
        return None
    total, last = 0.0, 0.0
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            elapsed = float(row["time_s"])
            if elapsed < last:  # a resumed segment restarts its clock
                total += last
            last = elapsed
    return total + last


def _obs_sizes(critic_state: dict[str, torch.Tensor]) -> tuple[int, int]:
    """(K, N) from a critic's state dict (its first layer's width and the normaliser's shape)."""
    num_targets = critic_state["normalizer.targets.mean"].shape[0]
    in_dim = critic_state["net.0.weight"].shape[1]
    return num_targets, (in_dim - PROPRIO_DIM - num_targets * TARGET_DIM) // 3


_ARCHITECTURE_FIELDS = ("scene_aware", "model", "normalize_obs")


def _check_resumable(saved: TrainConfig, cfg: TrainConfig, action: str = "resume") -> None:
    changed = [name for name in _ARCHITECTURE_FIELDS if getattr(saved, name) != getattr(cfg, name)]
    if changed:
        raise ValueError(f"cannot {action}: {', '.join(changed)} differ from the saved run's "
                         f"({', '.join(f'{n}={getattr(saved, n)!r}' for n in changed)})")


# --------------------------------------------------------------------------------------------
# Logging


def _tracker(kind: str, directory: Path):
    """A ``torchrl.record.loggers`` logger of ``kind`` writing under ``directory / "trackers"``."""
    from torchrl.record.loggers import get_logger  # noqa: PLC0415 - only runs that ask for trackers

    try:
        return get_logger(kind, logger_name=str(directory / "trackers"), experiment_name=directory.name)
    except ImportError as err:
        raise ModuleNotFoundError(f"--loggers {kind} needs the {err.name or kind} package: pip install "
                                  "'crisp-gym[tracking]' (TensorBoard, W&B) or the package itself") from None


class RunLogger:
    """``progress.csv`` rows, and the same scalars to TorchRL's experiment loggers (``kinds``)."""

    def __init__(self, directory: Path, append: bool, iteration: int = 0, extra_fields: tuple[str, ...] = (),
                 kinds: tuple[str, ...] = ()):
        self.path = directory / "progress.csv"
        self.fields = _CSV_FIELDS + tuple(extra_fields)
        new = not (append and self.path.exists())
        if not new:
            self._truncate(iteration)
        self._file = open(self.path, "w" if new else "a", newline="")
        self._csv = csv.DictWriter(self._file, fieldnames=self.fields, extrasaction="ignore")
        if new:
            self._csv.writeheader()
        self._trackers = [_tracker(kind, directory) for kind in kinds]

    def _truncate(self, iteration: int) -> None:
        """Drop rows after ``iteration``: a run that died between checkpoints logged
        iterations that resuming repeats."""
        with open(self.path, newline="") as f:
            reader = csv.DictReader(f)
            rows, header = list(reader), tuple(reader.fieldnames or ())
        if header != self.fields:
            raise ValueError(f"{self.path} has the columns {list(header)}, but this run logs {list(self.fields)}: "
                             f"resume with the clips the run started with")
        if all(int(row["iteration"]) <= iteration for row in rows):
            return
        with atomic_path(self.path) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(row for row in rows if int(row["iteration"]) <= iteration)

    def log(self, row: dict[str, float]) -> None:
        self._csv.writerow(row)
        self._file.flush()
        for tracker in self._trackers:
            for key, value in row.items():
                if key not in ("iteration", "frames") and isinstance(value, (int, float)) and math.isfinite(value):
                    tracker.log_scalar(key, float(value), step=int(row["frames"]))

    def close(self) -> None:
        self._file.close()
        for tracker in self._trackers:
            writer = getattr(tracker, "experiment", None)
            if hasattr(writer, "close"):  # TensorBoard's SummaryWriter holds its event file open
                writer.close()


def _clip_fields(clip_names: list[str], cfg: TrainConfig) -> tuple[str, ...]:
    """The per-clip columns of ``progress.csv``: the adaptive sampler's failure mass and, with
    periodic evaluation, the evaluation's success and frames from frame 0."""
    fields = [f"start_failures/{name}" for name in clip_names]
    if cfg.eval_every:
        fields += [f"eval_{kind}/{name}" for name in clip_names for kind in ("success", "frames")]
        fields += ["eval_success_min"]
    return tuple(fields)


def evaluation_score(results: dict[str, dict[str, float]]) -> float:
    """How good a periodic evaluation is, to keep the best weights: the mean over clips of the RSI
    success plus the share of the clip tracked from frame 0 (each in [0, 1])."""
    return float(sum(r["success"] + r["frames"] / r["num_frames"] for r in results.values()) / len(results))


def evaluation_score_of(checkpoint: dict[str, Any]) -> float:
    """:func:`evaluation_score` of the evaluation a checkpoint was saved at (from its run's log)."""
    return float(checkpoint.get("evaluation_score", -math.inf))


def _evaluation_row(results: dict[str, dict[str, float]]) -> dict[str, float]:
    row = {}
    for name, r in results.items():
        row[f"eval_success/{name}"] = r["success"]
        row[f"eval_frames/{name}"] = r["frames"]
    row["eval_success_min"] = min(r["success"] for r in results.values())
    return row


# --------------------------------------------------------------------------------------------
# Training


@dataclass
class TrainResult:
    """What :func:`train` returns.

    Attributes:
        iteration: iterations done in total (including those before a resume).
        frames: environment steps done in total.
        history: one dict per iteration of this call (the CSV rows).
        checkpoint: path of the last checkpoint.
        interrupted: training stopped early on Ctrl-C (the checkpoint holds the state then).
        reached_success: training stopped because an evaluation met ``until_success``.
    """

    iteration: int
    frames: int
    history: list[dict[str, float]]
    checkpoint: Path
    interrupted: bool = False
    reached_success: bool = False


@contextlib.contextmanager
def _stop_signals_interrupt() -> Iterator[None]:
    """SIGINT and SIGTERM end training like Ctrl-C, with a checkpoint.

    A job started in the background (``nohup crisp train ... &``) ignores SIGINT, and schedulers
    and sessions stop jobs with SIGTERM; both would otherwise lose the work since the last
    periodic checkpoint. Only the main thread can install handlers; elsewhere this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)
    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def actor_lr_at(iteration: int, start: int, ramp: int, lr: float) -> float:
    """The actor's learning rate at ``iteration`` of a warm-started run: 0 before ``start``, then
    rising linearly to ``lr`` over ``ramp`` iterations."""
    return lr * min(1.0, max(0, iteration - start + 1) / ramp)


def ppo_update(data: TensorDictBase, loss_module: nn.Module, optimizer: torch.optim.Optimizer, agent: Agent,
               cfg: TrainConfig, generator: torch.Generator, train_actor: bool = True) -> dict[str, float]:
    """``cfg.epochs`` passes of shuffled minibatches over a flat batch with advantages; mean losses.

    ``train_actor=False`` steps only the critic (the warm-up of a warm-started run).
    """
    n = data.numel()
    sums: dict[str, float] = {}
    steps = 0
    for _ in range(cfg.epochs):
        order = torch.randperm(n, generator=generator).to(data.device)
        for start in range(0, n, cfg.minibatch_size):
            batch = data[order[start:start + cfg.minibatch_size]]
            if cfg.normalize_advantage:
                batch.set("advantage", normalize_advantages(batch.get("advantage")))
            losses = loss_module(batch)
            loss = losses["loss_objective"] + losses["loss_critic"] if train_actor else losses["loss_critic"]
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(agent.actor.parameters(), cfg.max_grad_norm)
            nn.utils.clip_grad_norm_(agent.critic.parameters(), cfg.max_grad_norm)
            optimizer.step()
            for key in ("loss_objective", "loss_critic", "kl_approx", "clip_fraction", "explained_variance"):
                if key in losses.keys():
                    sums[key] = sums.get(key, 0.0) + float(losses[key].detach().mean())
            steps += 1
    return {key: value / steps for key, value in sums.items()}


def episode_stats(data: TensorDictBase) -> dict[str, float]:
    """Episodes that ended in ``data``: count, mean return and length, share that reached the clip's end."""
    done = data["next", "done"].reshape(-1)
    count = int(done.sum())
    if count == 0:
        return {"episodes": 0}
    return {
        "episodes": count,
        "mean_return": float(data["next", "episode_return"].reshape(-1)[done].mean()),
        "mean_length": float(data["next", "episode_length"].reshape(-1)[done].float().mean()),
        "success_rate": float(data["next", "success"].reshape(-1)[done].float().mean()),
    }


def _collector(cfg: TrainConfig, env: Any, env_fn: Callable[[TrainConfig, int], Any], agent: Agent,
               device: torch.device, iteration: int) -> Any:
    """TorchRL's ``Collector`` over ``env`` in this process, or with ``cfg.ray_workers`` its
    ``RayCollector``: one env per worker (from ``env_fn``), the policy's weights (observation
    statistics included) sent to every worker after each update."""
    if not cfg.ray_workers:
        from torchrl.collectors import Collector  # noqa: PLC0415

        return Collector(env, agent.policy, frames_per_batch=cfg.frames_per_iteration, total_frames=-1,
                         env_device="cpu", policy_device=device, storing_device=device,
                         auto_register_policy_transforms=False)
    try:
        import ray  # noqa: F401, PLC0415 - RayCollector imports it lazily, too late for a clear error
        from torchrl.collectors.distributed import RayCollector  # noqa: PLC0415
    except ModuleNotFoundError:
        raise ModuleNotFoundError("--ray-workers needs Ray: pip install 'crisp-gym[scale]'") from None
    cluster = {"address": cfg.ray_address} if cfg.ray_address else {"num_cpus": cfg.ray_workers}
    collector = RayCollector(
        [partial(env_fn, cfg, cfg.seed + 1000 * iteration + 1 + k) for k in range(cfg.ray_workers)],
        policy=agent.policy, frames_per_batch=cfg.ray_workers * cfg.frames_per_iteration,
        total_frames=2**62,  # the run stops on its own frame count
        sync=True, num_collectors=cfg.ray_workers,
        ray_init_config=cluster | {"include_dashboard": False, "log_to_driver": False},
        collector_kwargs={"env_device": "cpu", "policy_device": "cpu", "storing_device": "cpu"})
    collector.update_policy_weights_()
    return collector


def train(cfg: TrainConfig, env_fn: Callable[[TrainConfig, int], Any] | None = None) -> TrainResult:
    """Train (or, with ``cfg.resume``, continue training) a tracking policy; see the module docstring.

    Args:
        cfg: the run's configuration.
        env_fn: builds the TorchRL env from (config, seed); default :func:`make_env`. Profiling
            passes an instrumented env here.
    """
    from torchrl.objectives import ClipPPOLoss
    from torchrl.objectives.value import GAE

    out = Path(cfg.output)
    checkpoint_path = out / CHECKPOINT_NAME
    saved = None
    if cfg.resume:
        saved = load_checkpoint(checkpoint_path)
        _check_resumable(config_from_dict(saved["config"]), cfg)
    elif checkpoint_path.exists():
        raise FileExistsError(f"{checkpoint_path} exists: pass resume=True (--resume) to continue that run, "
                              f"or choose another output directory")
    warm = None  # the warm start's source (read on resume too: its warm-up schedule still applies)
    if cfg.init_from is not None:
        warm_path, warm = _read_policy_source(cfg.init_from)
        _check_resumable(config_from_dict(warm["config"]), cfg, f"initialise from {warm_path}")
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "config.json", json.dumps(_config_dict(cfg), indent=2) + "\n")

    device = resolve_device(cfg.device)
    if cfg.torch_threads > 0:
        torch.set_num_threads(cfg.torch_threads)
    iteration = saved["iteration"] if saved else 0
    frames = saved["frames"] if saved else 0
    torch.manual_seed(cfg.seed + iteration)
    generator = torch.Generator().manual_seed(cfg.seed)

    env = (env_fn or make_env)(cfg, cfg.seed + 1000 * iteration)
    spec = env.observation_spec
    num_targets = spec["targets"].shape[-2]
    num_points = spec["points"].shape[-2] if cfg.scene_aware else 0
    agent = build_agent(cfg.model, num_targets, num_points, cfg.normalize_obs, device)

    loss_module = ClipPPOLoss(agent.policy, agent.value, clip_epsilon=cfg.clip_epsilon, entropy_bonus=False,
                              loss_critic_type=cfg.critic_loss, normalize_advantage=False, functional=False)
    gae = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=None, average_gae=False)
    optimizer = torch.optim.Adam([
        {"params": list(agent.actor.parameters()), "lr": cfg.actor_lr},
        {"params": list(agent.critic.parameters()), "lr": cfg.critic_lr},
    ], fused=True)  # one kernel for all parameters: a few % of a CPU update
    if saved:
        agent.actor.load_state_dict(saved["actor"])
        agent.critic.load_state_dict(saved["critic"])
        optimizer.load_state_dict(saved["optimizer"])
        # the saved param groups carry the old learning rates: the config's must win on resume
        for group, lr in zip(optimizer.param_groups, (cfg.actor_lr, cfg.critic_lr)):
            group["lr"] = lr
        generator.set_state(saved["generator"])
        torch.set_rng_state(saved["torch_rng"])
    elif warm is not None:  # a new warm-started run (a resumed one has its weights in the checkpoint)
        agent.actor.load_state_dict(warm["actor"])  # the observation statistics come with it
        if "critic" in warm:
            agent.critic.load_state_dict(warm["critic"])
        if cfg.init_stats_samples is not None:
            agent.normalizer.limit_count(cfg.init_stats_samples)
    # a loaded actor with a fresh critic: let the critic learn its values before the actor moves
    critic_only_until = cfg.critic_warmup if warm is not None and "critic" not in warm else 0
    ramp = cfg.actor_lr_warmup if warm is not None else 0

    collector = _collector(cfg, env, env_fn or make_env, agent, device, iteration)
    clip_names = env.vec_env.task.clip_names
    sampler = env.vec_env.start_sampler
    best_score = evaluation_score_of(load_checkpoint(out / BEST_NAME)) if (out / BEST_NAME).is_file() else -math.inf
    if saved is not None and "start_failures" in saved:
        restored = [f.numpy().copy() for f in saved["start_failures"]]
        if [f.shape for f in restored] == [f.shape for f in sampler.failures]:
            sampler.failures = restored
    evaluation = None
    if cfg.eval_every:
        from train.evaluate import LibraryEvaluation, torch_policy

        evaluation = LibraryEvaluation(list(cfg.clip), cfg.eval_episodes, scene_aware=cfg.scene_aware, seed=cfg.seed,
                                       num_threads=cfg.num_threads, velocity_feedforward=cfg.velocity_feedforward)
    logger = RunLogger(out, append=cfg.resume, iteration=iteration, extra_fields=_clip_fields(clip_names, cfg),
                       kinds=cfg.loggers)
    history: list[dict[str, float]] = []
    last_episodes: dict[str, float] = {}
    bar = tqdm(total=cfg.frames, initial=min(frames, cfg.frames), unit="frame", unit_scale=True,
               disable=not cfg.progress, dynamic_ncols=True)
    start_time = time.perf_counter()
    stack = contextlib.ExitStack()
    interrupted = stopped_early = False
    try:
        stack.enter_context(_stop_signals_interrupt())
        batches = iter(collector)
        while frames < cfg.frames:
            collect_start, env_before = time.perf_counter(), env.env_time
            update_threads = torch.get_num_threads()
            if device.type == "cpu":
                # one step's forward pass is too small to split across threads: with two
                # threads on a busy 2-core machine it took 5x as long as with one
                torch.set_num_threads(1)
            data = next(batches)  # (num_envs, steps_per_env); on Ray (workers, num_envs, steps_per_env)
            if cfg.ray_workers:
                data = data.reshape(-1, data.shape[-1])
            torch.set_num_threads(update_threads)
            collect_s = time.perf_counter() - collect_start
            env_s = env.env_time - env_before

            update_start = time.perf_counter()
            if iteration == 0 and cfg.normalize_obs and warm is None:
                # The first batch only initialises the observation statistics: updating the
                # actor on raw (unnormalised) inputs would take oversized first steps. A warm
                # start brings its statistics.
                losses = {}
            else:
                with torch.no_grad():
                    estimate_values(data, agent.value)
                    gae(data)
                if ramp:
                    optimizer.param_groups[0]["lr"] = actor_lr_at(iteration, critic_only_until, ramp, cfg.actor_lr)
                losses = ppo_update(data.reshape(-1), loss_module, optimizer, agent, cfg, generator,
                                    train_actor=iteration >= critic_only_until)
            agent.normalizer.update(data["proprio"], data["targets"])
            collector.update_policy_weights_()
            update_s = time.perf_counter() - update_start

            iteration += 1
            frames += data.numel()
            stats = episode_stats(data)
            if stats["episodes"]:
                last_episodes = stats
            row = {"iteration": iteration, "frames": frames, "time_s": time.perf_counter() - start_time,
                   "fps": data.numel() / (collect_s + update_s), "collect_s": collect_s, "env_s": env_s,
                   "update_s": update_s, **losses, **last_episodes, "episodes": stats["episodes"]}
            row.update({f"start_failures/{name}": float(mass)
                        for name, mass in zip(clip_names, sampler.stats()["failure_mass"])})
            reached = False
            if evaluation is not None and iteration % cfg.eval_every == 0:
                results = evaluation(torch_policy(agent.actor, cfg.scene_aware, device))
                row.update(_evaluation_row(results))
                reached = cfg.until_success is not None and all(
                    r["success"] >= cfg.until_success and r["whole_clip"] for r in results.values())
                score = evaluation_score(results)
                if score > best_score:  # evaluations swing by tens of points: keep the best weights
                    best_score = score
                    save_checkpoint(out / BEST_NAME, agent, optimizer, iteration, frames, cfg, generator,
                                    sampler.failures, evaluation_score=score)
            history.append(row)
            logger.log(row)
            if evaluation is not None and iteration % cfg.eval_every == 0:
                from train.evaluate import plot_evaluations

                plot_evaluations(logger.path, out / "evaluation.png", dict(zip(evaluation.names, evaluation.num_frames)))
            bar.update(data.numel())
            bar.set_postfix(fps=f"{row['fps']:.0f}", ret=f"{last_episodes.get('mean_return', math.nan):.1f}",
                            len=f"{last_episodes.get('mean_length', math.nan):.0f}",
                            succ=f"{last_episodes.get('success_rate', math.nan):.2f}", refresh=False)
            if iteration % cfg.checkpoint_every == 0:
                save_checkpoint(checkpoint_path, agent, optimizer, iteration, frames, cfg, generator,
                                sampler.failures)
            if reached:
                bar.write(f"every clip reached {cfg.until_success:.0%} success from RSI starts and the whole clip "
                          f"from frame 0: stopping at {frames} frames")
                stopped_early = True
                break
    except KeyboardInterrupt:
        interrupted = True
        bar.write(f"interrupted: saving the checkpoint at iteration {iteration}", file=sys.stderr)
    finally:
        stack.close()
        bar.close()
        logger.close()
        collector.shutdown()
        if evaluation is not None:
            evaluation.close()
    # Only reached on completion or Ctrl-C: an error keeps the last periodic checkpoint.
    save_checkpoint(checkpoint_path, agent, optimizer, iteration, frames, cfg, generator,
                    env.vec_env.start_sampler.failures)
    return TrainResult(iteration, frames, history, checkpoint_path, interrupted, stopped_early)


# --------------------------------------------------------------------------------------------
# Command line


_PROFILES = {"paper": paper_profile, "cpu": cpu_profile}


def main(argv: list[str] | None = None) -> int:
    """``crisp train``: ``--profile {auto,paper,cpu}`` picks the defaults, every other flag
    is a :class:`TrainConfig` field (``--clip NAME --scene-aware --frames N --num-envs N -o RUN
    --resume``...). ``auto`` is ``paper`` when CUDA is available, else ``cpu``."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--profile", choices=("auto", *_PROFILES), default="auto")
    known, rest = pre.parse_known_args(argv)
    profile = known.profile
    if profile == "auto":
        profile = "paper" if torch.cuda.is_available() else "cpu"
    cfg = tyro.cli(TrainConfig, args=rest, default=_PROFILES[profile](), prog="crisp train",
                   description=f"Train a tracking policy with PPO (defaults: the {profile!r} profile; "
                               f"--profile {{auto,paper,cpu}} picks another).")
    result = train(cfg)
    print(f"{result.iteration} iterations, {result.frames} frames; checkpoint: {result.checkpoint}")
    return 130 if result.interrupted else 0


if __name__ == "__main__":
    raise SystemExit(main())
