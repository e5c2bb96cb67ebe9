"""Env throughput: the batched ``CrispTrack-v0`` against raw ``mujoco.batch`` physics.

Measured in one run on the same model:

* raw physics: ``Batch.step(nstep=substeps)`` with constant controls, in env-steps/s
  (one env-step = ``substeps`` physics steps), the ceiling the env can approach;
* the batched env (observation, reward, resets included), and its ratio to the above;
* the same ratio on the env's own states: the time the env spends in MuJoCo's batch calls
  (step, forward, reset) against its whole step time. The raw batch above holds constant
  controls from start states and is reset every 20 steps; the env's humanoids (zero residual
  actions: the PD reference) fall within about a second and make more contacts, so each of its
  physics steps costs more (about 15 % on ``flat_walk``) and the first ratio counts that as env
  overhead. The second counts only what the env adds to its own physics;
* with ``--policy``, the batched env driven by a trained policy instead (the states training
  sees once a policy tracks: humanoids upright, as in the raw batch); only ``env.step`` is
  timed, not the policy's inference;
* a single env, and gymnasium's ``SyncVectorEnv`` over single envs, for comparison.

    python benchmarks/env_fps.py --num-envs 64 --threads 2 --clip flat_walk
    python benchmarks/env_fps.py --num-envs 64 --threads 2 --clip bundled   # the motion library
    python benchmarks/env_fps.py --clip flat_walk --policy assets/policies/flat_walk
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import mujoco
import mujoco.batch
import numpy as np
import tyro

import crisp_gym  # noqa: F401  (registers CrispTrack-v0)
from crisp_gym.envs.track_vector import CrispTrackVectorEnv


@dataclass(frozen=True)
class Args:
    clip: tuple[str, ...] = ("flat_walk",)
    """one clip, a registry tag ("bundled") or several clips (a motion library)"""
    num_envs: int = 64
    threads: int = 2
    seconds: float = 5.0
    scene_aware: bool = False
    seed: int = 0
    policy: Path | None = None
    """also time the env driven by this trained policy (run directory, checkpoint or policy file)"""


def _rate(step, seconds: float) -> float:
    """Calls per second of ``step`` over about ``seconds`` (after a short warm-up)."""
    for _ in range(3):
        step()
    count, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        step()
        count += 1
    return count / (time.perf_counter() - start)


def _time_batch_calls(batch: mujoco.batch.Batch) -> dict:
    """Accumulate the seconds ``batch``'s step, forward and reset calls take from now on;
    ``["wall"]()`` is the time since."""
    timer = {"seconds": 0.0}
    start = time.perf_counter()
    for name in ("step", "forward", "reset"):
        call = getattr(batch, name)

        def timed(*args, _call=call, **kwargs):
            tic = time.perf_counter()
            try:
                return _call(*args, **kwargs)
            finally:
                timer["seconds"] += time.perf_counter() - tic

        setattr(batch, name, timed)
    timer["wall"] = lambda: time.perf_counter() - start
    return timer


def _policy_rate(venv: CrispTrackVectorEnv, policy_path: Path, seconds: float, seed: int) -> float:
    """Env-steps/s of ``venv.step`` alone while a trained policy picks the actions."""
    from crisp_gym.policy.files import load_actor
    from crisp_gym.train.rollouts import torch_policy

    loaded = load_actor(policy_path)
    if loaded.scene_aware != venv.config.scene_aware:
        raise SystemExit(f"{policy_path} is {'scene-aware' if loaded.scene_aware else 'scene-blind'}: "
                         f"pass {'--scene-aware' if loaded.scene_aware else '--no-scene-aware'}")
    act = torch_policy(loaded.actor, loaded.scene_aware)
    obs, _ = venv.reset(seed=seed)
    for _ in range(3):
        obs = venv.step(act(obs))[0]
    stepped, count, start = 0.0, 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        actions = act(obs)
        tic = time.perf_counter()
        obs = venv.step(actions)[0]
        stepped += time.perf_counter() - tic
        count += 1
    return count * venv.num_envs / stepped


def main(args: Args) -> dict[str, float]:
    rng = np.random.default_rng(args.seed)
    venv = CrispTrackVectorEnv(args.num_envs, clip=list(args.clip), scene_aware=args.scene_aware, num_threads=args.threads)
    venv.reset(seed=args.seed)
    substeps = venv.config.substeps

    raw = mujoco.batch.Batch(venv.model, args.num_envs, nthread=args.threads, persistent=True)
    qpos, qvel, ctrl = raw.bind("qpos"), raw.bind("qvel"), raw.bind("ctrl")
    clips, frames = venv.start_sampler.sample(rng, args.num_envs)
    qpos[:], qvel[:], ctrl[:] = venv.task.reset_state(clips, frames)
    raw.forward()

    def raw_step():
        raw.step(nstep=substeps, stage=mujoco.mjtStage.mjSTAGE_VEL)

    def reset_raw():  # keep the raw batch near the reference, as the env keeps resetting
        qpos[:], qvel[:], _ = venv.task.reset_state(clips, frames)
        raw.forward()

    zero = np.zeros((args.num_envs, venv.model.nu))
    results = {}
    raw_calls = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < args.seconds:
        for _ in range(20):
            raw_step()
        reset_raw()
        raw_calls += 20
    raw_rate = raw_calls * args.num_envs / (time.perf_counter() - t0)
    results["raw_physics_env_steps_per_s"] = raw_rate
    physics = _time_batch_calls(venv.batch)
    results["batched_env_steps_per_s"] = _rate(lambda: venv.step(zero), args.seconds) * args.num_envs
    results["ratio_batched_to_raw"] = results["batched_env_steps_per_s"] / raw_rate
    results["ratio_env_physics_to_env"] = physics["seconds"] / physics["wall"]()
    if args.policy is not None:
        results["policy_env_steps_per_s"] = _policy_rate(venv, args.policy, args.seconds, args.seed)
        results["ratio_policy_to_raw"] = results["policy_env_steps_per_s"] / raw_rate

    single = gym.make("CrispTrack-v0", clip=list(args.clip), scene_aware=args.scene_aware)
    single.reset(seed=args.seed)
    zero1 = np.zeros(venv.model.nu)

    def single_step():
        _, _, term, trunc, _ = single.step(zero1)
        if term or trunc:
            single.reset()

    results["single_env_steps_per_s"] = _rate(single_step, args.seconds)
    sync = gym.vector.SyncVectorEnv([lambda: gym.make("CrispTrack-v0", clip=list(args.clip), scene_aware=args.scene_aware)
                                     for _ in range(min(args.num_envs, 16))])
    sync.reset(seed=args.seed)
    zero_sync = np.zeros((sync.num_envs, venv.model.nu))
    results["sync_vector_env_steps_per_s"] = _rate(lambda: sync.step(zero_sync), args.seconds) * sync.num_envs
    sync.close()
    single.close()
    venv.close()

    print(f"\nCrispTrack-v0 on {', '.join(venv.task.clip_names)}, {args.num_envs} envs, {args.threads} threads, "
          f"{substeps} substeps, scene_aware={args.scene_aware}\n")
    print("| what | env-steps/s |\n|---|---|")
    for key in ("raw_physics_env_steps_per_s", "batched_env_steps_per_s", "policy_env_steps_per_s",
                "single_env_steps_per_s", "sync_vector_env_steps_per_s"):
        if key in results:
            print(f"| {key} | {results[key]:,.0f} |")
    print(f"| ratio batched / raw | {results['ratio_batched_to_raw']:.3f} |")
    print(f"| ratio on the env's own states: physics time / env step time | "
          f"{results['ratio_env_physics_to_env']:.3f} |")
    if "ratio_policy_to_raw" in results:
        print(f"| ratio batched, policy actions / raw | {results['ratio_policy_to_raw']:.3f} |")
    return results


if __name__ == "__main__":
    main(tyro.cli(Args))
