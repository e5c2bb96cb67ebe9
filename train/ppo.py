"""PPO for ``CrispTrack-v0``, written to be read top to bottom (in the spirit of single-file PPOs).

Pieces, all from TorchRL except the env adapter:

* env: :class:`~crisp_gym.train.env.CrispTrackTorchEnv` around the batched ``CrispTrack-v0``;
* collection: ``torchrl.collectors.Collector`` (``num_envs × steps_per_env`` frames per
  iteration, trajectories continue across iterations), or its ``MultiSyncCollector`` over
  ``collector_workers`` processes (:mod:`crisp_gym.train.workers`);
* advantages: ``torchrl.objectives.value.GAE`` (γ = 0.99, λ = 0.95) on values from
  :func:`estimate_values` (one critic pass per batch instead of GAE's two), normalised per
  minibatch by :func:`normalize_advantages`;
* loss: ``torchrl.objectives.ClipPPOLoss`` (no entropy bonus: σ is fixed);
* optimiser: one Adam with two parameter groups (actor lr 2e-5 as in the paper; critic lr
  1e-4, our choice: the paper gives a single rate, and the critic's regression targets move
  much faster than the policy should);
* precision: with ``precision="bfloat16"`` the forward passes of collection, value estimation
  and the loss run under ``torch.autocast`` (:func:`precision_context`); everything else stays
  float32.

Each iteration: collect → GAE → ``epochs`` passes of shuffled minibatches → update the
observation normaliser from the batch (after the update, so the minibatches see the
statistics the behaviour policy used) → log → every ``checkpoint_every`` iterations an atomic
checkpoint (temp file, then rename). ``resume=True`` continues from the output directory's
checkpoint (weights, normaliser, optimiser, iteration and frame counts).

Outputs in ``output``: ``config.json``, ``checkpoint.pt``, ``progress.csv`` and, with
``loggers``, the same scalars through TorchRL's experiment loggers (``torchrl.record.loggers``:
CSV, TensorBoard, W&B, MLflow) under ``output/trackers``.

Around this file: :mod:`crisp_gym.train.config` (the config and its profiles),
:mod:`crisp_gym.train.checkpoints`, :mod:`crisp_gym.train.run_log` and :mod:`crisp_gym.train.cli`
(``crisp train``); the networks are :mod:`crisp_gym.policy.networks`.
"""

from __future__ import annotations

import contextlib
import json
import math
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from tqdm.auto import tqdm

from crisp_gym.atomic import write_text
from crisp_gym.policy.files import BEST_NAME, CHECKPOINT_NAME, load_checkpoint, read_policy_source
from crisp_gym.policy.model_config import ModelConfig
from crisp_gym.policy.networks import Critic, FixedStdGaussian, ObsNormalizer, build_actor
from crisp_gym.train.checkpoints import (check_resumable, evaluation_meets, evaluation_score, evaluation_score_of,
                                         save_checkpoint)
from crisp_gym.train.config import TrainConfig, config_from_dict, config_to_dict, native_bfloat16
from crisp_gym.train.rollouts import LibraryEvaluation, single_cpu_thread, torch_policy
from crisp_gym.train.run_log import RunLogger, clip_fields, confirmation_row, evaluation_row
from crisp_gym.train.workers import STOP_SIGNALS, SharedStartCounts, worker_collector, worker_config


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
    actor = FixedStdGaussian(build_actor(model, num_targets, num_points, normalizer), model.action_std)
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
    from crisp_gym.train.env import CrispTrackTorchEnv, TrainingReward

    vec_env = gym.make_vec("CrispTrack-v0", num_envs=cfg.num_envs, vectorization_mode="vector_entry_point",
                           clip=list(cfg.clip), scene_aware=cfg.scene_aware, num_threads=cfg.num_threads,
                           clip_weights=cfg.clip_weights, start_sampling=cfg.start_sampling,
                           clip_sampling=cfg.clip_sampling, velocity_feedforward=cfg.velocity_feedforward,
                           w_root_pos=cfg.root_pos_weight)
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


def precision_context(precision: str, device: torch.device) -> contextlib.AbstractContextManager:
    """Where the networks run: bfloat16 autocast for ``precision="bfloat16"``, else nothing."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bfloat16")


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


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


class StopSignals:
    """SIGINT and SIGTERM end training like Ctrl-C, with a checkpoint.

    A job started in the background (``nohup crisp train ... &``) ignores SIGINT, and schedulers
    and sessions stop jobs with SIGTERM; both would otherwise lose the work since the last
    periodic checkpoint. Only the main thread can install handlers; elsewhere this does nothing.

    Inside :meth:`deferred` a signal is held until the block ends, so that an iteration's update,
    its counters and its ``progress.csv`` row land together, and so that worker processes being
    started are stopped once they can be; a second signal stops at once.
    """

    def __init__(self) -> None:
        self._previous: dict[int, Any] = {}
        self._deferring = False
        self._pending: str | None = None
        self._until = "this iteration"

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._interrupt) for sig in STOP_SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _interrupt(self, signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        if self._deferring and self._pending is None:
            self._pending = name
            print(f"{name}: stopping after {self._until} (again to stop at once)", file=sys.stderr)
            return
        raise KeyboardInterrupt(name)

    @contextlib.contextmanager
    def deferred(self, until: str = "this iteration") -> Iterator[None]:
        self._until = until
        self._deferring = True
        try:
            yield
        finally:
            self._deferring = False
        if self._pending is not None:
            raise KeyboardInterrupt(self._pending)


def actor_lr_at(iteration: int, start: int, ramp: int, lr: float) -> float:
    """The actor's learning rate at ``iteration`` of a warm-started run: 0 before ``start``, then
    rising linearly to ``lr`` over ``ramp`` iterations."""
    return lr * min(1.0, max(0, iteration - start + 1) / ramp)


def ppo_update(data: TensorDictBase, loss_module: nn.Module, optimizer: torch.optim.Optimizer, agent: Agent,
               cfg: TrainConfig, generator: torch.Generator, train_actor: bool = True) -> dict[str, float]:
    """``cfg.epochs`` passes of shuffled minibatches over a flat batch with advantages; mean losses.

    ``train_actor=False`` steps only the critic (the warm-up of a warm-started run). The forward
    passes run in ``cfg.precision``; the backward pass follows them (autocast's rule).
    """
    keys = loss_module.tensor_keys
    # only what the loss reads: each minibatch's indexing would otherwise copy the next observations too
    data = data.select(*agent.value.in_keys, keys.action, keys.sample_log_prob, keys.advantage, keys.value_target)
    n = data.numel()
    sums: dict[str, float] = {}
    steps = 0
    device = next(agent.actor.parameters()).device  # (a batch gathered from Ray workers has none)
    for _ in range(cfg.epochs):
        order = torch.randperm(n, generator=generator).to(data.device)
        for start in range(0, n, cfg.minibatch_size):
            batch = data[order[start:start + cfg.minibatch_size]]
            if cfg.normalize_advantage:
                batch.set("advantage", normalize_advantages(batch.get("advantage")))
            with precision_context(cfg.precision, device):
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
               device: torch.device, iteration: int, counts: SharedStartCounts | None) -> Any:
    """TorchRL's ``Collector`` over ``env`` in this process; with ``cfg.worker_processes`` its
    ``MultiSyncCollector`` (:func:`~crisp_gym.train.workers.worker_collector`, the start counts
    in ``counts``); or with ``cfg.ray_workers`` its ``RayCollector``: one env per worker (from
    ``env_fn``). Workers get the policy's weights (observation statistics included) after each
    update."""
    if cfg.worker_processes:
        return worker_collector(cfg, env_fn, agent.policy, counts, cfg.seed + 1000 * iteration + 1)
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


def _load_start_state(agent: Agent, optimizer: torch.optim.Optimizer, generator: torch.Generator,
                      cfg: TrainConfig, saved: dict[str, Any] | None, warm: dict[str, Any] | None) -> None:
    """Where a run starts: a resumed run's checkpoint (weights, optimiser, random state), else a
    warm start's weights and observation statistics, else nothing (fresh weights)."""
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
    agent.actor.std.fill_(cfg.model.action_std)  # the run's exploration noise, not the loaded one


def train(cfg: TrainConfig, env_fn: Callable[[TrainConfig, int], Any] | None = None) -> TrainResult:
    """Train (or, with ``cfg.resume``, continue training) a tracking policy; see the module docstring.

    Args:
        cfg: the run's configuration.
        env_fn: builds the TorchRL env from (config, seed); default :func:`make_env`. Profiling
            passes an instrumented env here. With collector worker processes every worker
            builds its own with it, so it must be picklable (a module-level function).
    """
    from torchrl.objectives import ClipPPOLoss
    from torchrl.objectives.value import GAE

    out = Path(cfg.output)
    checkpoint_path = out / CHECKPOINT_NAME
    saved = None
    if cfg.resume:
        saved = load_checkpoint(checkpoint_path)
        check_resumable(config_from_dict(saved["config"]), cfg)
    elif checkpoint_path.exists():
        raise FileExistsError(f"{checkpoint_path} exists: pass resume=True (--resume) to continue that run, "
                              f"or choose another output directory")
    warm = None  # the warm start's source (read on resume too: its warm-up schedule still applies)
    if cfg.init_from is not None:
        warm_path, warm = read_policy_source(cfg.init_from)
        check_resumable(config_from_dict(warm["config"]), cfg, f"initialise from {warm_path}")
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "config.json", json.dumps(config_to_dict(cfg), indent=2) + "\n")

    device = resolve_device(cfg.device)
    if cfg.precision == "bfloat16" and device.type == "cpu" and not native_bfloat16():
        warnings.warn("precision='bfloat16' on a CPU without native bfloat16 (AVX512-BF16 or AMX): torch "
                      "emulates it, and training runs slower than in float32", stacklevel=2)
    if cfg.torch_threads > 0:
        torch.set_num_threads(cfg.torch_threads)
    iteration = saved["iteration"] if saved else 0
    frames = saved["frames"] if saved else 0
    torch.manual_seed(cfg.seed + iteration)
    generator = torch.Generator().manual_seed(cfg.seed)

    # with worker processes this env is never stepped: it gives the specs and sums the start counts
    env = (env_fn or make_env)(worker_config(cfg) if cfg.worker_processes else cfg, cfg.seed + 1000 * iteration)
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
    _load_start_state(agent, optimizer, generator, cfg, saved, warm)
    # a loaded actor with a fresh critic: let the critic learn its values before the actor moves
    critic_only_until = cfg.critic_warmup if warm is not None and "critic" not in warm else 0
    ramp = cfg.actor_lr_warmup if warm is not None else 0

    clip_names = env.vec_env.task.clip_names
    sampler = env.vec_env.start_sampler
    counts = SharedStartCounts(sampler, cfg.worker_processes) if cfg.worker_processes else None
    best_score = evaluation_score_of(load_checkpoint(out / BEST_NAME)) if (out / BEST_NAME).is_file() else -math.inf
    if saved is not None and "start_failures" in saved:
        restored = [f.numpy() for f in saved["start_failures"]]
        if [f.shape for f in restored] == [f.shape for f in sampler.failures]:
            for kept, failures in zip(sampler.failures, restored):
                kept[:] = failures
            if counts is not None:
                counts.scatter()
    evaluation = confirmation = collector = None
    evaluation_env = dict(scene_aware=cfg.scene_aware, num_threads=cfg.num_threads,
                          velocity_feedforward=cfg.velocity_feedforward)
    if cfg.eval_every:
        evaluation = LibraryEvaluation(list(cfg.clip), cfg.eval_episodes, seed=cfg.seed, **evaluation_env)
    confirming = cfg.until_success is not None and cfg.confirm_episodes > 0
    logger = RunLogger(out, append=cfg.resume, iteration=iteration,
                       extra_fields=clip_fields(clip_names, bool(cfg.eval_every)),
                       kinds=cfg.loggers)
    history: list[dict[str, float]] = []
    last_episodes: dict[str, float] = {}
    bar = tqdm(total=cfg.frames, initial=min(frames, cfg.frames), unit="frame", unit_scale=True,
               disable=not cfg.progress, dynamic_ncols=True)
    start_time = time.perf_counter()
    stack = contextlib.ExitStack()
    interrupted = stopped_early = False
    try:
        stop_signals = stack.enter_context(StopSignals())
        with stop_signals.deferred("the workers start"):  # then they can be stopped
            collector = _collector(cfg, env, env_fn or make_env, agent, device, iteration, counts)
        batches = iter(collector)
        while frames < cfg.frames:
            collect_start, env_before = time.perf_counter(), env.env_time
            # with two threads a forward pass took 5x as long on a busy machine
            with single_cpu_thread(device), precision_context(cfg.precision, device):
                data = next(batches)  # (num_envs, steps_per_env); from workers (workers, envs each, steps)
            if cfg.ray_workers or cfg.worker_processes:
                data = data.reshape(-1, data.shape[-1]).to(device)
            if counts is not None:
                counts.gather()
            collect_s = time.perf_counter() - collect_start
            env_s = math.nan if cfg.worker_processes else env.env_time - env_before  # (not seen in the workers)

            with stop_signals.deferred():  # the update, the counters and the row land together
                update_start = time.perf_counter()
                if iteration == 0 and cfg.normalize_obs and warm is None:
                    # The first batch only initialises the observation statistics: updating the
                    # actor on raw (unnormalised) inputs would take oversized first steps. A warm
                    # start brings its statistics.
                    losses = {}
                else:
                    with torch.no_grad(), precision_context(cfg.precision, device):
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
                sampling = sampler.stats()
                row.update({f"start_failures/{name}": float(mass)
                            for name, mass in zip(clip_names, sampling["failure_mass"])})
                row.update({f"clip_probability/{name}": float(p)
                            for name, p in zip(clip_names, sampling["clip_probability"])})
                reached = False
                if evaluation is not None and iteration % cfg.eval_every == 0:
                    policy = torch_policy(agent.actor, cfg.scene_aware, device)
                    results = evaluation(policy)
                    row.update(evaluation_row(results))
                    reached = cfg.until_success is not None and evaluation_meets(results, cfg.until_success)
                    if reached and confirming:
                        if confirmation is None:  # other starts than the periodic evaluation's
                            confirmation = LibraryEvaluation(list(cfg.clip), cfg.confirm_episodes, seed=cfg.seed + 1,
                                                             **evaluation_env)
                        confirmed = confirmation(policy)
                        row.update(confirmation_row(confirmed))
                        reached = evaluation_meets(confirmed, cfg.until_success)
                        lowest = min(r["success"] for r in confirmed.values())
                        bar.write(f"{cfg.eval_episodes} RSI starts per clip reached {cfg.until_success:.0%}; "
                                  f"{cfg.confirm_episodes} other starts {'confirm' if reached else 'do not'} "
                                  f"(lowest clip {lowest:.0%})")
                    score = evaluation_score(results)
                    # Evaluations swing by tens of points: keep the best weights, or those that met
                    # the stop rule (an earlier evaluation as good may have failed its confirmation).
                    if score > best_score or reached:
                        best_score = score
                        save_checkpoint(out / BEST_NAME, agent, optimizer, iteration, frames, cfg, generator,
                                        sampler.failures, evaluation_score=score)
                history.append(row)
                logger.log(row)
            if evaluation is not None and iteration % cfg.eval_every == 0:
                from crisp_gym.train.plots import plot_evaluations

                plot_evaluations(logger.path, out / "evaluation.png",
                                 dict(zip(evaluation.names, evaluation.num_frames)))
            bar.update(data.numel())
            bar.set_postfix(fps=f"{row['fps']:.0f}", ret=f"{last_episodes.get('mean_return', math.nan):.1f}",
                            len=f"{last_episodes.get('mean_length', math.nan):.0f}",
                            succ=f"{last_episodes.get('success_rate', math.nan):.2f}", refresh=False)
            if iteration % cfg.checkpoint_every == 0:
                save_checkpoint(checkpoint_path, agent, optimizer, iteration, frames, cfg, generator,
                                sampler.failures)
            if reached:
                checked = f"{cfg.eval_episodes} RSI starts"
                checked += f" and {cfg.confirm_episodes} others" if confirming else ""
                bar.write(f"every clip reached {cfg.until_success:.0%} success from {checked} and the whole clip "
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
        if collector is not None:
            collector.shutdown()
        if counts is not None:
            counts.close()
        for evaluator in (evaluation, confirmation):
            if evaluator is not None:
                evaluator.close()
    # Only reached on completion or Ctrl-C: an error keeps the last periodic checkpoint.
    save_checkpoint(checkpoint_path, agent, optimizer, iteration, frames, cfg, generator,
                    env.vec_env.start_sampler.failures)
    return TrainResult(iteration, frames, history, checkpoint_path, interrupted, stopped_early)
