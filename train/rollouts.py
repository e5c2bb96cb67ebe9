"""Roll-outs of a policy in ``CrispTrack-v0``: the policy adapters, batched episodes from start frames
(success rates, throughput), the library evaluation run during training, and one recorded
episode from frame 0 (positions, rewards, torques, optional video frames)."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm.auto import tqdm

from crisp_gym.envs.tracking import servo_torque, terms_from_info
from crisp_gym.humanoid import BODY_NAMES
from crisp_gym.policy.networks import ACTION_DIM
from crisp_gym.train.tracking_metrics import accel_error, jitter, segment_mpjpe

# A policy maps the observation dict of one or more envs to their actions (numpy in, numpy out).
Policy = Callable[[dict[str, np.ndarray]], np.ndarray]


@contextlib.contextmanager
def single_cpu_thread(device: torch.device | str = "cpu") -> Iterator[None]:
    """Run torch on one CPU thread inside the block (on a CPU ``device``), as many as before after it.

    For the forward passes between simulation steps: a step's forward pass is too small to gain
    from a second thread, and torch's worker threads keep spinning after it, taking cores from
    MuJoCo's threads while they step the batch (``env.step`` ran 17 % slower beside them).
    """
    if torch.device(device).type != "cpu":
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def torch_policy(actor: nn.Module, scene_aware: bool, device: torch.device | str = "cpu") -> Policy:
    """A :data:`Policy` from an actor returning action means, or (mean, scale) as
    :class:`~crisp_gym.policy.networks.FixedStdGaussian` does; the mean is the action.
    It runs on one CPU thread (:func:`single_cpu_thread`)."""
    keys = ["proprio", "targets", "points"] if scene_aware else ["proprio", "targets"]

    @torch.no_grad()
    def act(obs: dict[str, np.ndarray]) -> np.ndarray:
        with single_cpu_thread(device):
            out = actor(*(torch.as_tensor(obs[k], device=device) for k in keys))
        mean = out[0] if isinstance(out, tuple) else out
        return mean.cpu().numpy()
    return act


def zero_policy(obs: dict[str, np.ndarray]) -> np.ndarray:
    """The PD-reference baseline: zero residual, i.e. the reference pose as the PD target."""
    return np.zeros((*obs["proprio"].shape[:-1], ACTION_DIM), dtype=np.float32)


@dataclass(frozen=True)
class EvalResult:
    """Per-episode outcome of :func:`evaluate`.

    Attributes:
        returns: (S,) undiscounted episode returns.
        lengths: (S,) episode lengths (steps).
        success: (S,) the episode reached the clip's last frame.
        start_frames: (S,) the episodes' start frames.
        seconds: wall time of the batched rollout (policy and simulation).
        clips: (S,) the episodes' clip indices (into the env's ``task.clip_names``).
        end_bodies: (S,) the body farthest from its reference at each episode's last step
            (index into ``crisp_gym.humanoid.BODY_NAMES``): for a failed episode, the one that
            ended it.
    """

    returns: np.ndarray
    lengths: np.ndarray
    success: np.ndarray
    start_frames: np.ndarray
    seconds: float
    clips: np.ndarray
    end_bodies: np.ndarray

    @property
    def mean_return(self) -> float:
        return float(self.returns.mean())

    @property
    def success_rate(self) -> float:
        return float(self.success.mean())

    @property
    def fps(self) -> float:
        """Env-steps per second of the episodes (steps after an episode's end are not counted)."""
        return float(self.lengths.sum() / self.seconds)

    @property
    def end_frames(self) -> np.ndarray:
        """(S,) the reference frame each episode ended at."""
        return self.start_frames + self.lengths


def failure_clusters(end_frames: np.ndarray, failed: np.ndarray, end_bodies: np.ndarray | None = None, *,
                     gap: int = 3, min_episodes: int = 2) -> list[dict[str, Any]]:
    """Frames where failed episodes pile up: the failed episodes' end frames, sorted and split
    wherever two are more than ``gap`` frames apart; groups of at least ``min_episodes`` as
    ``{"first_frame", "last_frame", "episodes"}``, most episodes first. With ``end_bodies``
    (each episode's :attr:`EvalResult.end_bodies`) a group also says which bodies ended its
    episodes: ``"bodies"``, body name to count, most first.

    Episodes started at different frames that end at the same place mark a part of the clip
    the controller cannot get through, whatever its state on the way there.
    """
    failed = np.asarray(failed, dtype=bool)
    failed_ends = np.asarray(end_frames)[failed]
    order = np.argsort(failed_ends, kind="stable")
    ends = failed_ends[order]
    if len(ends) == 0:
        return []
    failed_bodies = None if end_bodies is None else np.asarray(BODY_NAMES)[np.asarray(end_bodies)[failed]]
    splits = np.flatnonzero(np.diff(ends) > gap) + 1
    clusters = []
    for frames, members in zip(np.split(ends, splits), np.split(order, splits), strict=True):
        if len(frames) < min_episodes:
            continue
        cluster: dict[str, Any] = {"first_frame": int(frames[0]), "last_frame": int(frames[-1]),
                                   "episodes": len(frames)}
        if failed_bodies is not None:
            names, counts = np.unique(failed_bodies[members], return_counts=True)
            cluster["bodies"] = {str(names[i]): int(counts[i]) for i in np.argsort(-counts, kind="stable")}
        clusters.append(cluster)
    return sorted(clusters, key=lambda c: (-c["episodes"], c["first_frame"]))


def run_episodes(policy: Policy, env: Any, *, seed: int = 0, options: dict | None = None) -> EvalResult:
    """One episode per simulation of a batched ``CrispTrack-v0`` (``env``), from the starts that
    ``env.reset(seed=seed, options=options)`` gives; steps until every episode has ended.

    The env's autoreset starts new episodes in finished simulations; they are not counted.
    """
    start = time.perf_counter()
    obs, info = env.reset(seed=seed, options=options)
    count = env.num_envs
    returns = np.zeros(count)
    lengths = np.zeros(count, dtype=int)
    success = np.zeros(count, dtype=bool)
    end_bodies = np.zeros(count, dtype=int)
    running = np.ones(count, dtype=bool)
    while running.any():
        obs, reward, terminated, truncated, step_info = env.step(policy(obs))
        returns += np.where(running, reward, 0.0)
        lengths += running
        success |= running & truncated
        ending = running & (terminated | truncated)
        end_bodies[ending] = step_info["farthest_body"][ending]
        running &= ~ending
    return EvalResult(returns, lengths, success, info["start_frame"], time.perf_counter() - start, info["clip"],
                      end_bodies)


@torch.no_grad()
def evaluate(actor: nn.Module | Policy, clip: str | os.PathLike, start_frames: int | list[int] | np.ndarray, *,
             scene_aware: bool = False, seed: int = 0, device: torch.device | str = "cpu",
             **env_kwargs: Any) -> EvalResult:
    """Roll ``actor``'s mean action out once from each start frame, all in one batched env.

    Args:
        actor: a torch actor (action means, or (mean, scale)) or a :data:`Policy`.
        clip: clip name or directory.
        start_frames: reference frames to start from, or a number of episodes whose start
            frames the env draws as in training (reference state init, seeded by ``seed``).
        scene_aware: pass the ``points`` observation.
        seed: env seed (only the drawn start frames depend on it: the rollouts are deterministic).
        device: where a torch ``actor`` lives.
        **env_kwargs: further ``CrispTrack-v0`` options.
    """
    import gymnasium as gym

    import crisp_gym  # noqa: F401  (registers CrispTrack-v0)

    policy = torch_policy(actor, scene_aware, device) if isinstance(actor, nn.Module) else actor
    if np.ndim(start_frames) == 0:
        count, options = int(start_frames), {}
    else:
        frames = np.asarray(start_frames, dtype=int)
        if frames.ndim != 1:
            raise ValueError("start_frames must be a number of episodes or a 1-D list of frame indices")
        count, options = len(frames), {"start_frame": frames}
    if count < 1:
        raise ValueError(f"at least one episode is needed, got {count}")
    env = gym.make_vec("CrispTrack-v0", num_envs=count, vectorization_mode="vector_entry_point", clip=clip,
                       scene_aware=scene_aware, **env_kwargs)
    try:
        return run_episodes(policy, env, seed=seed, options=options)
    finally:
        env.close()


class LibraryEvaluation:
    """The same deterministic test of every clip of a library, repeated during training.

    Per clip: ``episodes`` RSI starts drawn once (uniform reference state init, seeded) plus
    one episode from frame 0, all in one batched env. Calling it with a policy returns, per
    clip name, ``success`` (share of the RSI episodes that reached the clip's end), ``frames``
    (frames tracked from frame 0), ``num_frames`` (the clip's; the whole clip is
    ``num_frames - 1`` steps) and ``whole_clip``.
    """

    def __init__(self, clip: Any, episodes: int, *, scene_aware: bool = False, seed: int = 0,
                 num_threads: int = 0, **env_kwargs: Any):
        from crisp_gym.envs.config import TrackConfig
        from crisp_gym.envs.start_sampler import StartSampler
        from crisp_gym.envs.track_vector import CrispTrackVectorEnv

        probe = CrispTrackVectorEnv(1, clip=clip)
        self.names = probe.task.clip_names
        self.num_frames = probe.task.num_frames.copy()
        probe.close()
        per_clip = episodes + 1
        self.clips = np.repeat(np.arange(len(self.names)), per_clip)
        sampler = StartSampler(self.num_frames, TrackConfig())
        _, drawn = sampler.sample(np.random.default_rng(seed), len(self.clips), clips=self.clips)
        drawn[::per_clip] = 0  # each clip's first episode: the whole clip from frame 0
        self.frames = drawn
        self.first_frame = np.zeros(len(self.clips), dtype=bool)
        self.first_frame[::per_clip] = True
        self.env = CrispTrackVectorEnv(len(self.clips), clip=clip, scene_aware=scene_aware, num_threads=num_threads,
                                       **env_kwargs)
        self.scene_aware = scene_aware

    @torch.no_grad()
    def __call__(self, policy: Policy) -> dict[str, dict[str, float]]:
        result = run_episodes(policy, self.env, options={"clip": self.clips, "start_frame": self.frames})
        out = {}
        for c, name in enumerate(self.names):
            rsi = (self.clips == c) & ~self.first_frame
            whole = (self.clips == c) & self.first_frame
            out[name] = {"success": float(result.success[rsi].mean()),
                         "frames": int(result.lengths[whole][0]),
                         "num_frames": int(self.num_frames[c]),
                         "whole_clip": bool(result.success[whole][0])}
        return out

    def close(self) -> None:
        self.env.close()


@dataclass
class Rollout:
    """One episode recorded frame by frame (:func:`record_rollout`).

    Attributes:
        body_pos: (T+1, 24, 3) simulated body origins (m), from the start frame on.
        ref_body_pos: (T+1, 24, 3) the reference's.
        max_body_error: (T+1,) largest body distance from the reference (m).
        rewards: (T,) env rewards.
        reward_terms: name → (T,) weighted reward terms.
        torques: (T, 69) servo torques (N·m; PD force and passive damping) at the end of each control step.
        success: the episode reached the clip's last frame.
        start_frame: the reference frame it started from.
        num_frames: frames in the clip.
        control_hz: steps per second.
        termination_distance: the early-termination threshold (m).
        images: rendered frames (empty unless rendering was asked for).
    """

    body_pos: np.ndarray
    ref_body_pos: np.ndarray
    max_body_error: np.ndarray
    rewards: np.ndarray
    reward_terms: dict[str, np.ndarray]
    torques: np.ndarray
    success: bool
    start_frame: int
    num_frames: int
    control_hz: float
    termination_distance: float
    images: list[np.ndarray] = field(default_factory=list)

    @property
    def steps(self) -> int:
        return len(self.rewards)

    def metrics(self) -> dict[str, Any]:
        """Success, frames tracked and the tracking metrics of the module docstring."""
        pred, ref = self.body_pos, self.ref_body_pos
        out: dict[str, Any] = {
            "success": bool(self.success),
            "start_frame": self.start_frame,
            "frames_tracked": self.steps,
            "frames_total": self.num_frames - 1 - self.start_frame,
            "return": float(self.rewards.sum()),
            "mpjpe_mm": segment_mpjpe(pred, ref, "none"),
            "w_mpjpe_mm": segment_mpjpe(pred, ref, "first_two"),
            "wa_mpjpe_mm": segment_mpjpe(pred, ref, "segment"),
            "mean_max_body_error_m": float(self.max_body_error.mean()),
        }
        if len(pred) >= 4:
            out["jitter_m_s3"] = jitter(pred, self.control_hz)
            out["reference_jitter_m_s3"] = jitter(ref, self.control_hz)
            out["accel_error_mm_frame2"] = accel_error(pred, ref)
        out["mean_reward_terms"] = {k: float(v.mean()) for k, v in self.reward_terms.items()}
        out["mean_abs_torque_nm"] = float(np.abs(self.torques).mean()) if self.steps else 0.0
        out["max_abs_torque_nm"] = float(np.abs(self.torques).max()) if self.steps else 0.0
        return out


def record_rollout(policy: Policy, clip: str | os.PathLike, start_frame: int = 0, *, render: bool = False,
                   scene_aware: bool = False, progress: bool = True, **env_kwargs: Any) -> Rollout:
    """One episode of ``policy`` in the single env from ``start_frame``, recorded frame by frame.

    With ``render`` every frame is drawn with the reference as a ghost (before each step, and
    the last state after the episode ends).
    """
    import gymnasium as gym

    import crisp_gym  # noqa: F401  (registers CrispTrack-v0)
    from crisp_gym.render import GhostRenderer

    env = gym.make("CrispTrack-v0", clip=clip, scene_aware=scene_aware, **env_kwargs).unwrapped
    renderer = None
    try:
        obs, info = env.reset(options={"start_frame": start_frame})
        reference, body_ids = env.task.reference, env.task.body_ids
        renderer = GhostRenderer(env.model, env.config.render_width, env.config.render_height) if render else None
        body_pos, ref_pos = [env.data.xpos[body_ids].copy()], [reference.body_pos[start_frame]]
        errors, rewards, terms, torques, images = [info["max_body_error"]], [], [], [], []
        frame, success = start_frame, False
        num_frames = int(env.task.num_frames[0])  # a one-clip library: its frames are the reference's rows
        steps = num_frames - 1 - start_frame
        for _ in tqdm(range(steps), desc="rollout", unit="step", disable=not progress, leave=False):
            if renderer is not None:
                images.append(renderer.render(env.data, reference.qpos[frame]))
            action = policy({k: v[None] for k, v in obs.items()})[0]
            obs, reward, terminated, truncated, info = env.step(action)
            body_pos.append(env.data.xpos[body_ids].copy())
            frame = info["frame"]
            ref_pos.append(reference.body_pos[frame])
            errors.append(info["max_body_error"])
            rewards.append(reward)
            terms.append(terms_from_info(info))
            torques.append(servo_torque(env.data.actuator_force, env.data.qfrc_damper))
            if terminated or truncated:
                success = bool(info["success"])
                break
        if renderer is not None:
            images.append(renderer.render(env.data, reference.qpos[frame]))
        return Rollout(
            body_pos=np.asarray(body_pos), ref_body_pos=np.asarray(ref_pos), max_body_error=np.asarray(errors),
            rewards=np.asarray(rewards), torques=np.asarray(torques).reshape(-1, env.model.nu),
            reward_terms={k: np.array([t[k] for t in terms]) for k in (terms[0] if terms else {})},
            success=success, start_frame=start_frame, num_frames=num_frames,
            control_hz=env.config.control_hz, termination_distance=env.config.termination_distance,
            images=images)
    finally:
        if renderer is not None:
            renderer.close()
        env.close()
