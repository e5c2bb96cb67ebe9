"""End-to-end PPO training throughput, scene-blind and scene-aware, and where the time goes.

Each variant runs :func:`crisp_gym.train.ppo.train` for ``--warmup`` iterations (not counted; they
include the normaliser-only first batch), then for enough iterations to collect ``--frames``
frames, and splits the wall-clock time of the measured iterations into:

* physics: ``mujoco.batch`` stepping, forward and reset calls;
* observation: the rest of the env's step (controls, observations, rewards, resets);
* inference: the policy's forward pass and sampling plus the collector's bookkeeping;
* update: GAE, the PPO epochs and the normaliser update.

    python benchmarks/train_fps.py                      # CPU profile, MLP and transformer actors
    python benchmarks/train_fps.py --profile paper --num-envs 2048 --actors transformer
    python benchmarks/train_fps.py --actors mlp --no-baseline --point-encoders pointnet flat
    python benchmarks/train_fps.py --actors mlp --no-baseline --precisions float32 bfloat16
    python benchmarks/train_fps.py --actors mlp --no-baseline --collector-workers 0 2

With collector workers the env runs in other processes, so such a variant gets its FPS and
update share only. The clip defaults to the bundled ``flat_walk``; ``--clip`` takes any
registered name or directory.
The baseline, measured first in the same run, is the CPU profile as it was before its
networks and batch shapes were resized (scene-blind MLP actor (512, 512), critic (1024, 512),
64 envs × 128 steps, one 8,192-sample minibatch, 2 epochs); every row also gets its ratio to it.
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import tyro

from crisp_gym.policy.model_config import ModelConfig
from crisp_gym.registry import resolve_clip
from crisp_gym.train.config import TrainConfig, cpu_profile, paper_profile
from crisp_gym.train.ppo import make_env, train

BASELINE = {"num_envs": 64, "steps_per_env": 128, "minibatch_size": 8192, "epochs": 2, "scene_aware": False,
            "torch_threads": 0, "collector_workers": 0,
            "model": ModelConfig(actor="mlp", mlp_actor_hidden=(512, 512), critic_hidden=(1024, 512))}


@dataclass(frozen=True)
class Args:
    """Benchmark options.

    Attributes:
        clip: clip name or directory.
        profile: ``cpu`` or ``paper`` defaults for everything not set here.
        actors: actor architectures to measure.
        scene: which variants to measure (``blind``, ``aware``).
        point_encoders: the scene-aware variants' point encoders (``pointnet``, ``flat``; default:
            the profile's).
        precisions: the networks' precisions to measure every variant in (``float32``,
            ``bfloat16``; default: the profile's).
        collector_workers: the collector worker processes to measure every variant with (0:
            collection in the trainer's process; default: the profile's).
        frames: frames measured per variant (rounded up to whole iterations).
        warmup: iterations run before measuring.
        baseline: also measure the baseline (see the module docstring) and give ratios to it.
        num_envs: override the profile's env count (0: keep).
        steps_per_env: override the profile's roll-out length (0: keep).
        epochs: override the profile's PPO epochs (0: keep).
        device: torch device (``auto``: CUDA when available).
        torch_threads: override the profile's torch intra-op threads (0: keep).
        seed: run seed.
    """

    clip: str = "flat_walk"
    profile: str = "cpu"
    actors: tuple[str, ...] = ("mlp", "transformer")
    scene: tuple[str, ...] = ("blind", "aware")
    point_encoders: tuple[str, ...] = ()
    precisions: tuple[str, ...] = ()
    collector_workers: tuple[int, ...] = ()
    frames: int = 16384
    warmup: int = 2
    baseline: bool = True
    num_envs: int = 0
    steps_per_env: int = 0
    epochs: int = 0
    device: str = "auto"
    torch_threads: int = 0
    seed: int = 0


class _TimedBatch:
    """Delegates to a ``mujoco.batch.Batch`` and adds up the time of its stepping calls."""

    def __init__(self, batch):
        self._batch = batch
        self.seconds = 0.0

    def _timed(self, name: str):
        method = getattr(self._batch, name)

        def call(*args, **kwargs):
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - start
        return call

    def __getattr__(self, name: str):
        if name in ("step", "forward", "reset"):
            return self._timed(name)
        return getattr(self._batch, name)


def measure(cfg: TrainConfig, warmup: int) -> dict[str, float]:
    """Run ``cfg`` and return FPS and time shares over its iterations after ``warmup``."""
    batches: list[_TimedBatch] = []

    def env_fn(config: TrainConfig, seed: int):
        env = make_env(config, seed)
        env.vec_env.batch = _TimedBatch(env.vec_env.batch)
        batches.append(env.vec_env.batch)
        return env

    threads = torch.get_num_threads()
    try:
        # worker processes build their envs themselves: nothing of theirs can be timed here
        result = train(cfg, env_fn=None if cfg.worker_processes else env_fn)
    finally:
        torch.set_num_threads(threads)  # train() sets the process-wide count from the config
    rows = result.history[warmup:]
    if not rows:
        raise ValueError("no measured iterations: raise --iterations")
    collect = sum(r["collect_s"] for r in rows)
    update = sum(r["update_s"] for r in rows)
    total = collect + update
    frames = sum(cfg.frames_per_iteration for _ in rows)
    shares = {"physics": math.nan, "observation": math.nan, "inference": math.nan}
    if not cfg.worker_processes:
        env_s = sum(r["env_s"] for r in rows)
        # physics is only known in total: apportion it to the measured iterations by env time
        physics = batches[0].seconds * env_s / sum(r["env_s"] for r in result.history)
        shares = {"physics": physics / total, "observation": (env_s - physics) / total,
                  "inference": (collect - env_s) / total}
    return {"fps": frames / total, **shares, "update": update / total, "iteration_s": total / len(rows)}


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(Args, args=argv)
    base = {"cpu": cpu_profile, "paper": paper_profile}[args.profile]()
    overrides = {k: v for k, v in (("num_envs", args.num_envs), ("steps_per_env", args.steps_per_env),
                                   ("epochs", args.epochs), ("torch_threads", args.torch_threads)) if v}
    default_threads = torch.get_num_threads()
    print(f"torch threads by default: {default_threads}, device: {args.device}, profile: {args.profile}")
    variants = [("baseline", "blind", replace(base, **BASELINE))] if args.baseline else []
    encoders = {"blind": (base.model.point_encoder,), "aware": args.point_encoders or (base.model.point_encoder,)}
    variants += [(actor, scene, replace(base, scene_aware=scene == "aware", precision=precision,
                                        collector_workers=workers,
                                        model=replace(base.model, actor=actor, point_encoder=encoder), **overrides))
                 for actor in args.actors for scene in args.scene for encoder in encoders[scene]
                 for precision in args.precisions or (base.precision,)
                 for workers in args.collector_workers or (base.collector_workers,)]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        clip = str(resolve_clip(args.clip))
        for name, scene, variant in variants:
            cfg = replace(variant, clip=clip,
                          output=Path(tmp) / (f"{name}-{scene}-{variant.model.point_encoder}-{variant.precision}"
                                              f"-{variant.collector_workers}"),
                          device=args.device, seed=args.seed, progress=False, checkpoint_every=10**9)
            iterations = -(-args.frames // cfg.frames_per_iteration)
            cfg = replace(cfg, frames=(args.warmup + iterations) * cfg.frames_per_iteration)
            stats = measure(cfg, args.warmup)
            rows.append((name, scene, cfg, stats))
            print(f"  {scene:5s} {name:11s} {cfg.precision:8s} workers {cfg.worker_processes} "
                  f"{stats['fps']:8.0f} frames/s", flush=True)
    reference = rows[0][3]["fps"] if args.baseline else None
    print()
    print("| variant | actor | critic | envs × steps | minibatch × epochs | torch threads | precision | workers | FPS "
          "| × baseline "
          "| physics | observation | inference | update |")
    print("|---|---|---|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, scene, cfg, s in rows:
        actor = cfg.model.actor + (str(cfg.model.mlp_actor_hidden) if cfg.model.actor == "mlp" else "")
        ratio = f"{s['fps'] / reference:.2f}" if reference else "–"
        label = "baseline" if name == "baseline" else f"scene-{scene}"
        if cfg.scene_aware:
            label += f" ({cfg.model.point_encoder})"
        print(f"| {label} | {actor} | {cfg.model.critic_hidden} | "
              f"{cfg.num_envs} × {cfg.steps_per_env} | {cfg.minibatch_size} × {cfg.epochs} | "
              f"{cfg.torch_threads or default_threads} | {cfg.precision} | {cfg.worker_processes} | "
              f"{s['fps']:.0f} | {ratio} | "
              + " | ".join("–" if math.isnan(s[k]) else f"{s[k]:.0%}"
                           for k in ("physics", "observation", "inference", "update")) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
