"""Deterministic evaluation of a tracking policy from chosen start frames.

One simulation per start frame, all in one batched ``CrispTrack-v0``; each runs one episode
with the policy's mean action (no exploration noise) and is then ignored.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn


@dataclass(frozen=True)
class EvalResult:
    """Per-start-frame outcome of :func:`evaluate`.

    Attributes:
        returns: (S,) undiscounted episode returns.
        lengths: (S,) episode lengths (steps).
        success: (S,) the episode reached the clip's last frame.
    """

    returns: np.ndarray
    lengths: np.ndarray
    success: np.ndarray

    @property
    def mean_return(self) -> float:
        return float(self.returns.mean())

    @property
    def success_rate(self) -> float:
        return float(self.success.mean())


@torch.no_grad()
def evaluate(actor: nn.Module, clip: str | os.PathLike, start_frames: list[int] | np.ndarray, *,
             scene_aware: bool = False, seed: int = 0, device: torch.device | str = "cpu",
             **env_kwargs: Any) -> EvalResult:
    """Roll ``actor`` out once from each of ``start_frames``.

    Args:
        actor: maps (proprio, targets[, points]) tensors to action means, or to (mean, scale)
            (as :class:`~train.models.FixedStdGaussian` does).
        clip: clip name or directory.
        start_frames: reference frames to start from (reference state init).
        scene_aware: pass the ``points`` observation.
        seed: env seed (the env is deterministic given the start frames; kept for completeness).
        device: where ``actor`` lives.
        **env_kwargs: further ``CrispTrack-v0`` options.
    """
    import gymnasium as gym

    import crisp_gym  # noqa: F401  (registers CrispTrack-v0)

    frames = np.asarray(start_frames, dtype=int)
    if frames.ndim != 1 or len(frames) == 0:
        raise ValueError("start_frames must be a non-empty 1-D list of frame indices")
    env = gym.make_vec("CrispTrack-v0", num_envs=len(frames), vectorization_mode="vector_entry_point", clip=clip,
                       scene_aware=scene_aware, **env_kwargs)
    try:
        obs, _ = env.reset(seed=seed, options={"start_frame": frames})
        returns = np.zeros(len(frames))
        lengths = np.zeros(len(frames), dtype=int)
        success = np.zeros(len(frames), dtype=bool)
        running = np.ones(len(frames), dtype=bool)
        keys = ["proprio", "targets", "points"] if scene_aware else ["proprio", "targets"]
        while running.any():
            out = actor(*(torch.as_tensor(obs[k], device=device) for k in keys))
            mean = out[0] if isinstance(out, tuple) else out
            obs, reward, terminated, truncated, info = env.step(mean.cpu().numpy())
            returns += np.where(running, reward, 0.0)
            lengths += running
            success |= running & truncated
            running &= ~(terminated | truncated)
    finally:
        env.close()
    return EvalResult(returns, lengths, success)
