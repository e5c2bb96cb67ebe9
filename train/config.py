"""The configuration of a training run (:class:`TrainConfig`), its two profiles and its plain-value form.

``paper_profile`` is the paper's setup for a GPU machine; ``cpu_profile`` one for a small CPU
machine, where the PPO update, not physics, is the cost. A checkpoint and a policy file keep the
config as plain values (:func:`config_to_dict`, :func:`config_from_dict`).
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Annotated, Any

import tyro

from crisp_gym.policy.model_config import ModelConfig, model_config

PRECISIONS = ("float32", "bfloat16")
"""What ``TrainConfig.precision`` may name."""

LOGGERS = ("csv", "tensorboard", "wandb", "mlflow")
"""The experiment loggers of ``torchrl.record.loggers`` that ``TrainConfig.loggers`` may name."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs; defaults are the paper's values where it gives them.

    Attributes:
        clip: clips to train on: names (registry), registry tags (bundled: every bundled
            clip) or clip directories; several make a motion library.
        clip_weights: relative probability of each clip at a reset (None: equal).
        start_sampling: "uniform" reference state init or "adaptive" (starts drawn
            where episodes recently failed; crisp_gym.envs.start_sampler).
        clip_sampling: "fixed" (clips drawn by clip_weights) or "adaptive" (mixed with each
            clip's weight times its recent failure rate: the library's hardest clips get more
            episodes; crisp_gym.envs.start_sampler).
        output: run directory (config, checkpoint, CSV log).
        scene_aware: train the scene-aware policy (points observation, PointNet tokens).
        velocity_feedforward: PD targets lead the reference by the servos' kd/kp times its hinge
            velocities, so fast moves are not lagged by the servos' damping (the env option of
            the same name).
        root_pos_weight: weight of the env's pelvis-position reward term (``w_root_pos``; 0, the
            default, is the paper's reward): the summed position term stops pulling a body that
            has drifted 0.1-0.2 m back to its reference, this term does not.
        frames: total environment steps (the paper does not state its budget).
        num_envs: parallel simulations (paper: 2048).
        steps_per_env: steps collected per simulation and iteration (horizon of the GAE
            segments; frames per iteration = num_envs × steps_per_env).
        minibatch_size: samples per gradient step (paper: 8192).
        epochs: passes over each iteration's batch.
        gamma: discount (paper: 0.99).
        gae_lambda: GAE λ (paper: τ = 0.95).
        clip_epsilon: PPO ratio clip.
        actor_lr: actor learning rate (paper: 2e-5).
        critic_lr: critic learning rate (not in the paper; see the module docstring).
        max_grad_norm: gradient-norm clip, applied to actor and critic separately.
        critic_loss: "l2" or "smooth_l1".
        normalize_advantage: normalise advantages per minibatch (zero mean, unit std).
        normalize_obs: running observation normalisation (proprio and targets).
        reward_scale: factor on the rewards PPO learns from (not the logged returns); see
            TrainingReward.
        energy_cap: bound on the energy penalty's magnitude per step in the rewards PPO
            learns from (None: unbounded, as in the paper); see
            TrainingReward.
        model: actor/critic architecture (paper: transformer actor, [1024, 512] critic).
        seed: seeds torch, the minibatch shuffles and the env's start frames.
        device: "auto" (CUDA when available), "cpu", "cuda"...
        num_threads: MuJoCo threads stepping the batch (0: all CPUs).
        torch_threads: torch intra-op threads (0: torch's default).
        precision: "float32", or "bfloat16": the networks' hidden layers run in bfloat16
            (torch.autocast) while collecting and updating; weights, optimiser, observation
            statistics, output layers and the loss stay float32, and policy files are float32
            (evaluation runs in float32). On a CPU with native bfloat16 matrix units (AVX512-BF16,
            AMX) a CPU-profile update takes about half as long; elsewhere it is slower
            (native_bfloat16 tells). Worker processes and Ray workers collect in float32.
        checkpoint_every: iterations between checkpoints (one is also written at the end).
        eval_every: iterations between deterministic evaluations (the policy's mean action, per
            clip: success from eval_episodes fixed RSI starts and frames tracked from frame
            0), logged in progress.csv and evaluation.png; 0 disables them.
        eval_episodes: RSI episodes per clip in each evaluation (plus one from frame 0).
        until_success: stop once an evaluation finds every clip at this RSI success or more,
            and tracked from frame 0 to the end (None: train for frames).
        confirm_episodes: with until_success, an evaluation that meets it is repeated from this
            many other RSI starts per clip (another draw), and the run stops only if that one
            meets it too: a rule checked on a few starts at every evaluation passes by chance
            sooner or later. 0: no confirmation.
        init_from: warm start: a policy file, run directory or checkpoint whose actor (and,
            from a checkpoint, critic) weights and observation statistics start this run. Its
            architecture must match this run's.
        critic_warmup: with init_from and no critic in it, iterations that train only the
            critic, so a random critic's advantages do not undo the loaded actor.
        init_stats_samples: with init_from, the loaded observation statistics count as at
            most this many samples (None: as many as built them), so that the new clips'
            observations move them. The library's statistics come from synthetic clips whose
            arms barely move: a captured person's arm swing normalises to the ±5σ clip on dozens
            of features, and after 19.7 M samples new data barely shifts them.
        actor_lr_warmup: with init_from, iterations over which the actor's learning rate
            rises linearly from 0 once it starts training. Adam's first steps move every
            weight by the full learning rate whatever the gradient's size: from a trained
            actor the first update was measured at KL 0.15 with half the samples clipped
            (0.01–0.02 later), and a 97 %-success policy fell to 44 % within 0.5 M frames.
        resume: continue from output/checkpoint.pt.
        progress: show a progress bar.
        collector_workers: collect in this many worker processes on this machine, each
            stepping num_envs / collector_workers of the simulations on one MuJoCo thread and
            running the policy (in float32) on one torch thread; the iteration is the same as in
            one process. 0: in this process. On two cores, two workers keep both busy while
            collecting (see crisp_gym.train.workers). Not used when Ray collects (ray_workers).
        ray_workers: collect on this many Ray workers, each with its own batched env of
            num_envs simulations (an iteration then has ray_workers times the frames);
            0: in this process. Each worker's env keeps its own adaptive start sampler, so
            start_failures/* in progress.csv and the checkpoint stay empty.
        ray_address: a Ray cluster to collect on (auto, ray://HEAD:10001); default: a local
            one of ray_workers cores.
        loggers: experiment trackers that also get every progress.csv scalar (step: frames),
            through torchrl.record.loggers: csv, tensorboard, wandb, mlflow
            (the last three need their package: pip install 'crisp-gym[tracking]' has
            TensorBoard and W&B).
    """

    clip: tuple[str, ...] = ("flat_walk",)
    clip_weights: tuple[float, ...] | None = None
    start_sampling: str = "uniform"
    clip_sampling: str = "fixed"
    output: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("runs/track")
    scene_aware: bool = False
    velocity_feedforward: bool = False
    root_pos_weight: float = 0.0
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
    precision: str = "float32"
    checkpoint_every: int = 20
    eval_every: int = 0
    eval_episodes: int = 32
    until_success: float | None = None
    confirm_episodes: int = 100
    init_from: Path | None = None
    init_stats_samples: int | None = None
    critic_warmup: int = 20
    actor_lr_warmup: int = 100
    resume: bool = False
    progress: bool = True
    loggers: tuple[str, ...] = ()
    collector_workers: int = 0
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
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        if self.critic_loss not in ("l2", "smooth_l1"):
            raise ValueError(f"critic_loss must be 'l2' or 'smooth_l1', got {self.critic_loss!r}")
        if self.init_stats_samples is not None and self.init_stats_samples < 1:
            raise ValueError(f"init_stats_samples must be at least 1, got {self.init_stats_samples}")
        if min(self.eval_every, self.confirm_episodes, self.critic_warmup, self.actor_lr_warmup) < 0:
            raise ValueError("eval_every, confirm_episodes, critic_warmup and actor_lr_warmup must be non-negative")
        if self.until_success is not None and not (0 < self.until_success <= 1 and self.eval_every > 0):
            raise ValueError("until_success must be in (0, 1] and needs eval_every > 0")
        if self.ray_workers < 0 or (self.ray_address is not None and not self.ray_workers):
            raise ValueError("ray_workers must be at least 0, and ray_address needs ray_workers > 0")
        if self.collector_workers < 0 or (self.collector_workers and self.num_envs % self.collector_workers):
            raise ValueError(f"collector_workers must be at least 0 and divide num_envs ({self.num_envs}), "
                             f"got {self.collector_workers}")
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

    @property
    def worker_processes(self) -> int:
        """The collector worker processes on this machine: ``collector_workers``, none when Ray collects."""
        return 0 if self.ray_workers else self.collector_workers


def available_cpus() -> int:
    """The CPUs this process may run on (its affinity where the OS tells, else all)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def native_bfloat16() -> bool:
    """Whether this CPU multiplies bfloat16 matrices natively (AVX512-BF16 or AMX); elsewhere
    torch emulates them, slower than float32.

    On Linux the kernel's CPU flags tell (the CPU profile's defaults, and so ``crisp train
    --help``, need not import torch for them); elsewhere torch's own probes do.
    """
    flags = linux_cpu_flags()
    if flags is not None:
        return bool(flags & {"avx512_bf16", "amx_tile"})
    import torch

    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")  # torch.cpu's own probes
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)


def linux_cpu_flags(cpuinfo: str | Path = "/proc/cpuinfo") -> set[str] | None:
    """The CPU feature flags the Linux kernel lists for the first CPU (``None`` without the file)."""
    try:
        with open(cpuinfo) as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.partition(":")[2].split())
    except OSError:
        return None
    return set()


def paper_profile(**overrides: Any) -> TrainConfig:
    """The paper's setup (transformer actor, 2048 envs, batch 8192, lr 2e-5): for a GPU machine."""
    return replace(TrainConfig(), **overrides)


def cpu_profile(**overrides: Any) -> TrainConfig:
    """A setup for a small CPU machine (aimed at 2 cores), where the PPO update, not physics, is the cost.

    Small MLPs (actor and critic 256-256; scene-aware, the points encoded flat: ``FlatPoints``
    instead of a PointNet), 64 envs × 16 steps per iteration, 2 epochs of 512-sample minibatches,
    actor lr 3e-5 and critic lr 5e-4, rewards scaled by 0.05 with the energy penalty capped at 2
    per step, adaptive start sampling, a 20 M frame budget, an evaluation every 500 iterations,
    the hidden layers in bfloat16 where the CPU multiplies it natively (:func:`native_bfloat16`;
    float32 elsewhere; ``config.json`` records which), and, with two or more CPUs, collection in
    two worker processes (``collector_workers``). ``docs/training.md`` ("The CPU profile") gives
    the measurements behind each choice.

    Residual actions (the env's default) are kept: an untrained policy already tracks the
    reference pose with its PD targets, which matters most when few frames are affordable.
    """
    base = TrainConfig(num_envs=64, steps_per_env=16, minibatch_size=512, epochs=2, actor_lr=3e-5,
                       critic_lr=5e-4, reward_scale=0.05, energy_cap=2.0, frames=20_000_000, checkpoint_every=20,
                       start_sampling="adaptive", eval_every=500, eval_episodes=32,
                       precision="bfloat16" if native_bfloat16() else "float32",
                       collector_workers=2 if available_cpus() >= 2 else 0,
                       model=ModelConfig(actor="mlp", mlp_actor_hidden=(256, 256), critic_hidden=(256, 256),
                                         point_encoder="flat", pointnet_hidden=(32, 64)))
    return replace(base, **overrides)


PROFILES = {"paper": paper_profile, "cpu": cpu_profile}


def config_to_dict(cfg: TrainConfig) -> dict[str, Any]:
    """``cfg`` as JSON-ready plain values (what checkpoints, policy files and ``config.json`` hold)."""
    data = asdict(cfg)
    data["output"] = str(cfg.output)
    data["clip"] = list(cfg.clip)
    data["init_from"] = None if cfg.init_from is None else str(cfg.init_from)
    return data


def config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """Inverse of :func:`config_to_dict`. Keys added since a file was written take their
    defaults; a dict that is no such config (unknown keys, no ``output`` or ``model``: a damaged
    or foreign file) is a ValueError naming what is wrong."""
    data = dict(data)
    unknown = sorted(set(data) - {f.name for f in fields(TrainConfig)})
    missing = [key for key in ("output", "model") if key not in data]
    problems = ([f"unknown keys {unknown}"] if unknown else []) + (["no " + " or ".join(missing)] if missing else [])
    if problems:
        raise ValueError("not a training config: " + "; ".join(problems))
    try:
        model = model_config(data)
    except (TypeError, AttributeError) as err:
        raise ValueError(f"not a training config: its model settings do not fit ({err})") from None
    del data["model"]
    for key in ("clip", "clip_weights"):  # JSON keeps tuples as lists
        if isinstance(data.get(key), list):
            data[key] = tuple(data[key])
    if data.get("init_from") is not None:
        data["init_from"] = Path(data["init_from"])
    return TrainConfig(**{**data, "output": Path(data["output"]), "model": model})
