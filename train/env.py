"""A native TorchRL environment around the batched ``CrispTrack-v0``.

:class:`CrispTrackTorchEnv` is an ``EnvBase`` with ``batch_size = [num_envs]`` that steps a
:class:`~crisp_gym.envs.track_vector.CrispTrackVectorEnv`. It maps the vector env's
``SAME_STEP`` autoreset onto TorchRL's partial-reset protocol:

* ``step`` returns, for simulations whose episode just ended, the episode's *last*
  observation (``info["final_obs"]``) under ``"next"``, so value bootstrapping at truncation
  (the clip's end) sees the right state; the first observation of the next episode, which
  the vector env already computed, is kept aside.
* TorchRL then calls ``reset`` with ``"_reset"`` marking those simulations, and receives the
  kept observations: no simulation is stepped or reset twice.

Besides the observations (``proprio``, ``targets`` and, scene-aware, ``points``) every step
carries episode statistics for logging: ``episode_return`` and ``episode_length`` (running
values; the episode's totals on its last step) and ``success`` (the episode reached the
clip's last frame without early termination).

The ``reward`` PPO learns from may differ from the env's (see :class:`TrainingReward`); the
logged ``episode_return`` is always the env's own reward, so it compares across runs.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from crisp_gym.envs.track_vector import CrispTrackVectorEnv
from crisp_gym.envs.tracking import terms_from_info

STAT_KEYS = ("episode_return", "episode_length", "success")


@dataclass(frozen=True)
class TrainingReward:
    """How the env's reward becomes the reward PPO learns from.

    Attributes:
        scale: multiplies the reward (returns of O(1–10) are easier for the critic to regress
            than the env's O(100) ones; normalised advantages make the policy gradient
            independent of it).
        energy_cap: bound on the energy penalty's magnitude per step (``None``: unbounded, as
            in the paper). A falling humanoid's PD servos saturate and the penalty reaches
            several units per step, more than all tracking terms together: the rewards of a
            failing episode turn negative and ending it early starts to pay.
    """

    scale: float = 1.0
    energy_cap: float | None = None

    def __post_init__(self) -> None:
        if not self.scale > 0 or (self.energy_cap is not None and not self.energy_cap >= 0):
            raise ValueError(f"scale must be positive and energy_cap non-negative or None, got {self}")

    def __call__(self, reward: np.ndarray, terms: dict[str, np.ndarray]) -> np.ndarray:
        """(N,) training rewards from the env's rewards and their terms
        (:func:`~crisp_gym.envs.tracking.terms_from_info`)."""
        if self.energy_cap is not None:
            energy = terms["energy"]
            capped = reward - energy + np.maximum(energy, -self.energy_cap)
            reward = np.where(np.isfinite(capped), capped, reward)
        return self.scale * reward

    @property
    def is_identity(self) -> bool:
        return self.scale == 1.0 and (self.energy_cap is None or math.isinf(self.energy_cap))


class CrispTrackTorchEnv(EnvBase):
    """TorchRL view of a :class:`CrispTrackVectorEnv` (CPU tensors, float32 observations).

    Args:
        vec_env: the batched env; its ``autoreset_mode`` must be ``SAME_STEP``.
        seed: seed of the first full reset (later full resets continue the env's generator).
        reward: the training reward (default: the env's reward unchanged).

    Attributes:
        env_time: seconds spent inside the vector env's ``reset``/``step`` (physics and
            observations), for profiling.
    """

    def __init__(self, vec_env: CrispTrackVectorEnv, seed: int | None = None,
                 reward: TrainingReward = TrainingReward()):
        mode = getattr(vec_env, "autoreset_mode", None)
        if getattr(mode, "name", None) != "SAME_STEP":
            raise ValueError(f"the vector env must autoreset in SAME_STEP mode, got {mode!r}")
        n = vec_env.num_envs
        super().__init__(device="cpu", batch_size=torch.Size([n]))
        self.vec_env = vec_env
        self.num_envs = n
        self.obs_keys = tuple(vec_env.single_observation_space.spaces)
        obs_specs = {key: Unbounded((n, *space.shape), dtype=torch.float32)
                     for key, space in vec_env.single_observation_space.spaces.items()}
        self.observation_spec = Composite(
            **obs_specs,
            episode_return=Unbounded((n, 1), dtype=torch.float32),
            episode_length=Unbounded((n, 1), dtype=torch.int64),
            success=Categorical(2, (n, 1), dtype=torch.bool),
            shape=(n,),
        )
        self.action_spec = Bounded(-1.0, 1.0, (n, *vec_env.single_action_space.shape), dtype=torch.float32)
        self.reward_spec = Unbounded((n, 1), dtype=torch.float32)
        self.done_spec = Composite(
            done=Categorical(2, (n, 1), dtype=torch.bool),
            terminated=Categorical(2, (n, 1), dtype=torch.bool),
            truncated=Categorical(2, (n, 1), dtype=torch.bool),
            shape=(n,),
        )
        self._seed = seed
        self.training_reward = reward
        self._pending: dict[str, np.ndarray] | None = None  # next episodes' first observations
        self._needs_reset = np.ones(n, dtype=bool)
        self._return = np.zeros(n)
        self._length = np.zeros(n, dtype=np.int64)
        self.env_time = 0.0

    def _set_seed(self, seed: int | None) -> None:
        self._seed = seed

    def _obs_td(self, obs: dict[str, np.ndarray], ret: np.ndarray, length: np.ndarray,
                success: np.ndarray) -> TensorDict:
        data = {key: torch.from_numpy(np.ascontiguousarray(obs[key], dtype=np.float32)) for key in self.obs_keys}
        data["episode_return"] = torch.from_numpy(ret.astype(np.float32)).unsqueeze(-1)
        data["episode_length"] = torch.from_numpy(length.astype(np.int64)).unsqueeze(-1)
        data["success"] = torch.from_numpy(success).unsqueeze(-1)
        return TensorDict(data, batch_size=self.batch_size)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict["_reset"].reshape(self.num_envs).cpu().numpy()
        if mask is None or mask.all() and self._pending is None:
            start = time.perf_counter()
            obs, _ = self.vec_env.reset(seed=self._seed)
            self.env_time += time.perf_counter() - start
            self._seed = None
            self._pending = None
            self._needs_reset[:] = False
            self._return[:] = 0.0
            self._length[:] = 0
        else:
            if self._pending is None or np.any(mask & ~self._needs_reset):
                raise RuntimeError("the batched env can only reset simulations whose episode has just ended "
                                   "(or all of them at once)")
            obs = self._pending
            self._needs_reset &= ~mask
            self._return[mask] = 0.0
            self._length[mask] = 0
        zeros = np.zeros(self.num_envs, dtype=bool)
        return self._obs_td(obs, self._return, self._length, zeros)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._needs_reset.any():
            raise RuntimeError("step() called before the finished simulations were reset; "
                               "reset them with '_reset' (TorchRL's step_and_maybe_reset does this)")
        action = tensordict["action"].detach().cpu().numpy()
        start = time.perf_counter()
        obs, reward, terminated, truncated, info = self.vec_env.step(action)
        self.env_time += time.perf_counter() - start
        done = terminated | truncated
        self._return += reward
        self._length += 1
        next_obs = obs
        if done.any():
            self._pending = {key: value.copy() for key, value in obs.items()}
            next_obs = {key: value.copy() for key, value in obs.items()}
            for i in np.flatnonzero(done):
                for key in self.obs_keys:
                    next_obs[key][i] = info["final_obs"][i][key]
            self._needs_reset |= done
        out = self._obs_td(next_obs, self._return, self._length, np.asarray(info["success"], dtype=bool))
        if not self.training_reward.is_identity:
            reward = self.training_reward(reward, terms_from_info(info))
        out["reward"] = torch.from_numpy(reward.astype(np.float32)).unsqueeze(-1)
        out["done"] = torch.from_numpy(done).unsqueeze(-1)
        out["terminated"] = torch.from_numpy(terminated.astype(bool)).unsqueeze(-1)
        out["truncated"] = torch.from_numpy(truncated.astype(bool)).unsqueeze(-1)
        return out

    def _close(self, *, raise_if_closed: bool = True) -> None:
        if self.vec_env is not None:
            self.vec_env.close()
