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

Outputs in ``output``: ``config.json``, ``checkpoint.pt``, ``progress.csv`` and, when the
``tensorboard`` package is importable, TensorBoard event files.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Annotated, Any

import torch
import tyro
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from tqdm.auto import tqdm

from crisp_gym.atomic import atomic_path
from train.models import PROPRIO_DIM, TARGET_DIM, Critic, FixedStdGaussian, ModelConfig, ObsNormalizer, build_actor

CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_FORMAT = 1
POLICY_NAME = "policy.pt"
POLICY_FORMAT = 1
_CSV_FIELDS = ("iteration", "frames", "time_s", "fps", "episodes", "mean_return", "mean_length", "success_rate",
               "loss_objective", "loss_critic", "kl_approx", "clip_fraction", "explained_variance",
               "collect_s", "env_s", "update_s")


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs; defaults are the paper's values where it gives them.

    Attributes:
        clip: clip name (registry) or clip directory.
        output: run directory (config, checkpoint, CSV log).
        scene_aware: train the scene-aware policy (``points`` observation, PointNet tokens).
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
        resume: continue from ``output/checkpoint.pt``.
        progress: show a progress bar.
    """

    clip: str = "flat_walk"
    output: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("runs/track")
    scene_aware: bool = False
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
    resume: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        positive = ("num_envs", "steps_per_env", "minibatch_size", "epochs", "checkpoint_every")
        bad = [name for name in positive if getattr(self, name) < 1]
        if bad:
            raise ValueError(f"{', '.join(bad)} must be at least 1")
        if self.frames < 0:
            raise ValueError(f"frames must be non-negative, got {self.frames}")
        if not (0 < self.gamma <= 1 and 0 <= self.gae_lambda <= 1):
            raise ValueError("gamma must be in (0, 1] and gae_lambda in [0, 1]")
        if self.critic_loss not in ("l2", "smooth_l1"):
            raise ValueError(f"critic_loss must be 'l2' or 'smooth_l1', got {self.critic_loss!r}")

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
    * a 20 M frame budget.

    Residual actions (the env's default) are kept: an untrained policy already tracks the
    reference pose with its PD targets, which matters most when few frames are affordable.
    """
    base = TrainConfig(num_envs=64, steps_per_env=16, minibatch_size=512, epochs=2, actor_lr=3e-5,
                       critic_lr=5e-4, reward_scale=0.05, energy_cap=2.0, frames=20_000_000, checkpoint_every=20,
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
                           clip=cfg.clip, scene_aware=cfg.scene_aware, num_threads=cfg.num_threads)
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
    return data


def config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """Inverse of the ``config`` entry of a checkpoint (unknown keys are an error)."""
    data = dict(data)
    model = ModelConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.pop("model").items()})
    return TrainConfig(**{**data, "output": Path(data["output"]), "model": model})


def save_checkpoint(path: str | Path, agent: Agent, optimizer: torch.optim.Optimizer, iteration: int,
                    frames: int, cfg: TrainConfig, generator: torch.Generator) -> Path:
    """Write a checkpoint atomically (a temporary file, synced, then renamed over ``path``)."""
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
    state = torch.load(path, map_location="cpu", weights_only=True)
    if state.get("format_version") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a version-{CHECKPOINT_FORMAT} crisp-gym training checkpoint")
    return state


def load_policy(path: str | Path, device: torch.device | str = "cpu") -> tuple[FixedStdGaussian, TrainConfig]:
    """The trained actor ((loc, scale) from observations, normaliser included) and its config.

    ``path`` is a run directory (its ``policy.pt`` if it has one, else its ``checkpoint.pt``),
    a training checkpoint or a policy file written by :func:`export_policy`.
    """
    _, state = _read_policy_source(path)
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
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or not (
            state.get("kind") == "policy" and state.get("format_version") == POLICY_FORMAT
            or state.get("format_version") == CHECKPOINT_FORMAT and "critic" in state):
        raise ValueError(f"{path} is neither a crisp-gym training checkpoint nor a policy file "
                         f"(version {CHECKPOINT_FORMAT}/{POLICY_FORMAT})")
    return path, state


def export_policy(run: str | Path, output: str | Path, clip: str | None = None) -> Path:
    """Write a run's actor as a small self-contained policy file, ``output/policy.pt``.

    It holds the actor's ``state_dict`` (observation-normaliser statistics included), the
    run's config and its training totals (iterations, frames, wall time from
    ``progress.csv``): all :func:`load_policy` needs, without the critic and optimiser state
    that make a checkpoint several times larger.

    Args:
        run: run directory or checkpoint file.
        output: directory for ``policy.pt`` (created).
        clip: clip name to record in the config instead of the run's (e.g. a registered name
            in place of a machine-specific directory).
    """
    checkpoint = Path(run) / CHECKPOINT_NAME if Path(run).is_dir() else Path(run)
    state = load_checkpoint(checkpoint)
    config = dict(state["config"])
    if clip is not None:
        config["clip"] = clip
    payload = {
        "format_version": POLICY_FORMAT,
        "kind": "policy",
        "config": config,
        "actor": state["actor"],
        "training": policy_training_stats(checkpoint),
    }
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


def _check_resumable(saved: TrainConfig, cfg: TrainConfig) -> None:
    changed = [name for name in _ARCHITECTURE_FIELDS if getattr(saved, name) != getattr(cfg, name)]
    if changed:
        raise ValueError(f"cannot resume: {', '.join(changed)} differ from the checkpoint's "
                         f"({', '.join(f'{n}={getattr(saved, n)!r}' for n in changed)})")


# --------------------------------------------------------------------------------------------
# Logging


class RunLogger:
    """CSV rows (+ TensorBoard scalars when the ``tensorboard`` package is importable)."""

    def __init__(self, directory: Path, append: bool, iteration: int = 0):
        self.path = directory / "progress.csv"
        new = not (append and self.path.exists())
        if not new:
            self._truncate(iteration)
        self._file = open(self.path, "w" if new else "a", newline="")
        self._csv = csv.DictWriter(self._file, fieldnames=_CSV_FIELDS, extrasaction="ignore")
        if new:
            self._csv.writeheader()
        self._tb = None
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:  # tensorboard is optional
            pass
        else:
            self._tb = SummaryWriter(str(directory / "tb"))

    def _truncate(self, iteration: int) -> None:
        """Drop rows after ``iteration``: a run that died between checkpoints logged
        iterations that resuming repeats."""
        with open(self.path, newline="") as f:
            rows = list(csv.DictReader(f))
        if all(int(row["iteration"]) <= iteration for row in rows):
            return
        with atomic_path(self.path) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=_CSV_FIELDS, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(row for row in rows if int(row["iteration"]) <= iteration)

    def log(self, row: dict[str, float]) -> None:
        self._csv.writerow(row)
        self._file.flush()
        if self._tb is not None:
            for key, value in row.items():
                if key not in ("iteration", "frames") and isinstance(value, (int, float)) and math.isfinite(value):
                    self._tb.add_scalar(key, value, row["frames"])

    def close(self) -> None:
        self._file.close()
        if self._tb is not None:
            self._tb.close()


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
    """

    iteration: int
    frames: int
    history: list[dict[str, float]]
    checkpoint: Path
    interrupted: bool = False


def ppo_update(data: TensorDictBase, loss_module: nn.Module, optimizer: torch.optim.Optimizer, agent: Agent,
               cfg: TrainConfig, generator: torch.Generator) -> dict[str, float]:
    """``cfg.epochs`` passes of shuffled minibatches over a flat batch with advantages; mean losses."""
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
            loss = losses["loss_objective"] + losses["loss_critic"]
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


def train(cfg: TrainConfig, env_fn: Callable[[TrainConfig, int], Any] | None = None) -> TrainResult:
    """Train (or, with ``cfg.resume``, continue training) a tracking policy; see the module docstring.

    Args:
        cfg: the run's configuration.
        env_fn: builds the TorchRL env from (config, seed); default :func:`make_env`. Profiling
            passes an instrumented env here.
    """
    from torchrl.collectors import Collector
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
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(_config_dict(cfg), indent=2) + "\n")

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

    collector = Collector(env, agent.policy, frames_per_batch=cfg.frames_per_iteration, total_frames=-1,
                          env_device="cpu", policy_device=device, storing_device=device,
                          auto_register_policy_transforms=False)
    logger = RunLogger(out, append=cfg.resume, iteration=iteration)
    history: list[dict[str, float]] = []
    last_episodes: dict[str, float] = {}
    bar = tqdm(total=cfg.frames, initial=min(frames, cfg.frames), unit="frame", unit_scale=True,
               disable=not cfg.progress, dynamic_ncols=True)
    start_time = time.perf_counter()
    interrupted = False
    try:
        batches = iter(collector)
        while frames < cfg.frames:
            collect_start, env_before = time.perf_counter(), env.env_time
            update_threads = torch.get_num_threads()
            if device.type == "cpu":
                # one step's forward pass is too small to split across threads: with two
                # threads on a busy 2-core machine it took 5x as long as with one
                torch.set_num_threads(1)
            data = next(batches)  # (num_envs, steps_per_env)
            torch.set_num_threads(update_threads)
            collect_s = time.perf_counter() - collect_start
            env_s = env.env_time - env_before

            update_start = time.perf_counter()
            if iteration == 0 and cfg.normalize_obs:
                # The first batch only initialises the observation statistics: updating the
                # actor on raw (unnormalised) inputs would take oversized first steps.
                losses = {}
            else:
                with torch.no_grad():
                    estimate_values(data, agent.value)
                    gae(data)
                losses = ppo_update(data.reshape(-1), loss_module, optimizer, agent, cfg, generator)
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
            history.append(row)
            logger.log(row)
            bar.update(data.numel())
            bar.set_postfix(fps=f"{row['fps']:.0f}", ret=f"{last_episodes.get('mean_return', math.nan):.1f}",
                            len=f"{last_episodes.get('mean_length', math.nan):.0f}",
                            succ=f"{last_episodes.get('success_rate', math.nan):.2f}", refresh=False)
            if iteration % cfg.checkpoint_every == 0:
                save_checkpoint(checkpoint_path, agent, optimizer, iteration, frames, cfg, generator)
    except KeyboardInterrupt:
        interrupted = True
        bar.write(f"interrupted: saving the checkpoint at iteration {iteration}")
    finally:
        bar.close()
        logger.close()
        collector.shutdown()
    # Only reached on completion or Ctrl-C: an error keeps the last periodic checkpoint.
    save_checkpoint(checkpoint_path, agent, optimizer, iteration, frames, cfg, generator)
    return TrainResult(iteration, frames, history, checkpoint_path, interrupted)


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
