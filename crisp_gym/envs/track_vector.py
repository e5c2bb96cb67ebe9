"""The batched ``CrispTrack-v0``: all simulations stepped by one ``mujoco.batch.Batch`` call.

``gym.make_vec("CrispTrack-v0", num_envs=N, vectorization_mode="vector_entry_point", ...)``
returns it. Stepping releases the GIL inside MuJoCo's thread pool; a persistent batch keeps
one MjData per simulation, and ``stage=mjSTAGE_VEL`` leaves the derived fields at the new
state at no extra cost, which is what the observation reads.

Autoreset is ``SAME_STEP``: a finished simulation is reset inside the same ``step``; the
returned observation starts its next episode, and ``info["final_obs"]`` /
``info["final_info"]`` (masked by ``info["_final_obs"]``) hold the last one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import mujoco
import mujoco.batch
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from crisp_gym.envs.config import TrackConfig
from crisp_gym.envs.library import ClipSource
from crisp_gym.envs.task import TrackingTask
from crisp_gym.envs.track import make_config
from crisp_gym.envs.tracking import REWARD_TERMS, reward_info

_BOUND_FIELDS = ("qpos", "qvel", "ctrl", "xpos", "xquat", "cvel", "subtree_com", "actuator_force")


class CrispTrackVectorEnv(VectorEnv):
    """``num_envs`` copies of :class:`~crisp_gym.envs.track.CrispTrackEnv` in one batch.

    Observations, rewards, the ``info["reward_*"]`` terms, termination and success are those of
    the single env (the same functions over the same MuJoCo fields), batched on the first axis.
    With several clips (a motion library) all of them are composed into one model, so one
    ``mujoco.batch`` call still steps every simulation; ``info["clip"]`` says which clip each
    simulation tracks (indices into ``task.clip_names``).

    Args:
        num_envs: simulations in the batch.
        clip: clip name, registry tag or directory, or a list of them (see the single env).
        scene_aware: add the ``points`` observation.
        num_threads: MuJoCo threads stepping the batch (0: all CPUs).
        config, **overrides: as for the single env.

    ``reset(options={"start_frame": frames, "clip": clips})`` fixes the start frames and/or
    clips (scalars or one per simulation).
    """

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int = 1, clip: ClipSource | Sequence[ClipSource] = "flat_walk",
                 scene_aware: bool = False, num_threads: int = 0, config: TrackConfig | None = None,
                 render_mode: str | None = None, **overrides: Any):
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        if render_mode is not None:
            raise ValueError("the batched env does not render; use the single env for videos")
        self.config = make_config(config, {"scene_aware": scene_aware, **overrides})
        self.task = TrackingTask(clip, self.config)
        self.start_sampler = self.task.start_sampler()
        self.model = self.task.model
        self.num_envs = num_envs
        self.autoreset_mode = AutoresetMode.SAME_STEP
        self.batch = mujoco.batch.Batch(self.model, num_envs, nthread=num_threads, persistent=True)
        self._fields = {name: self.batch.bind(name) for name in _BOUND_FIELDS}
        self.single_observation_space = self.task.observation_space()
        self.single_action_space = self.task.action_space()
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._clip = np.zeros(num_envs, dtype=int)
        self._frame = np.zeros(num_envs, dtype=int)
        self._start_frame = np.zeros(num_envs, dtype=int)
        self._all = np.arange(num_envs)

    def _state(self, ids: np.ndarray | slice = slice(None)):
        f = {name: self._fields[name][ids] for name in _BOUND_FIELDS if name != "ctrl"}
        return self.task.read_state(f["qpos"], f["qvel"], f["xpos"], f["xquat"], f["cvel"], f["subtree_com"],
                                    f["actuator_force"])

    def _reset_sims(self, ids: np.ndarray, clips: np.ndarray, frames: np.ndarray) -> None:
        qpos, qvel, ctrl = self.task.reset_state(clips, frames)
        self.batch.reset(ids, stage=mujoco.mjtStage.mjSTAGE_NONE)
        self._fields["qpos"][ids] = qpos
        self._fields["qvel"][ids] = qvel
        self._fields["ctrl"][ids] = ctrl
        self.batch.forward(ids, stage=mujoco.mjtStage.mjSTAGE_VEL)
        self._clip[ids] = clips
        self._frame[ids] = frames
        self._start_frame[ids] = frames

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        forced = None
        if "clip" in options:
            given = np.broadcast_to(np.asarray(options["clip"], dtype=object), (self.num_envs,))
            forced = np.array([self.task.clip_index(c) for c in given])
        clips, frames = self.start_sampler.sample(self.np_random, self.num_envs, clips=forced)
        if "start_frame" in options:
            frames = np.broadcast_to(np.asarray(options["start_frame"], dtype=int), (self.num_envs,)).copy()
        self.task.check_starts(clips, frames)
        self._reset_sims(self._all, clips, frames)
        state = self._state()
        obs = self.task.observe(state, self._clip, self._frame)
        error = self.task.tracking_error(state, self._clip, self._frame)
        # The same keys as a step's info (terms zero, no success yet): wrappers that read infos
        # into fixed specs, e.g. TorchRL's GymWrapper, need them on every call.
        terms = reward_info({name: np.zeros(self.num_envs) for name in REWARD_TERMS})
        return obs, {"clip": self._clip.copy(), "frame": self._frame.copy(), "start_frame": self._start_frame.copy(),
                     **terms, "max_body_error": error, "success": np.zeros(self.num_envs, dtype=bool)}

    def step(self, actions):
        next_frame = self._frame + 1
        self._fields["ctrl"][:] = self.task.controls(np.asarray(actions).reshape(self.num_envs, -1), self._clip,
                                                     next_frame)
        try:
            self.batch.step(nstep=self.config.substeps, stage=mujoco.mjtStage.mjSTAGE_VEL)
            failed = np.zeros(self.num_envs, dtype=bool)
        except mujoco.batch.SimulationError as err:  # the others ran on; end the failed episodes
            failed = np.isin(self._all, err.ids)
        self._frame = next_frame
        state = self._state()
        reward, terms, terminated, truncated, error = self.task.evaluate(state, self._clip, next_frame)
        terminated = terminated | failed
        truncated = truncated & ~failed
        obs = self.task.observe(state, self._clip, next_frame)
        info: dict[str, Any] = {"clip": self._clip.copy(), "frame": next_frame.copy(),
                                "start_frame": self._start_frame.copy(), **reward_info(terms),
                                "max_body_error": error, "success": truncated.copy()}
        done = terminated | truncated
        if done.any():
            ids = np.flatnonzero(done)
            self.start_sampler.record(self._clip[ids], next_frame[ids], terminated[ids])
            info["final_obs"] = np.array([None] * self.num_envs, dtype=object)
            info["final_info"] = np.array([None] * self.num_envs, dtype=object)
            for i in ids:
                info["final_obs"][i] = {k: v[i].copy() for k, v in obs.items()}
                info["final_info"][i] = {"clip": int(self._clip[i]), "frame": int(next_frame[i]),
                                         "start_frame": int(self._start_frame[i]),
                                         "max_body_error": float(error[i]), "success": bool(truncated[i])}
            info["_final_obs"] = done.copy()
            info["_final_info"] = done.copy()
            self._reset_sims(ids, *self.start_sampler.sample(self.np_random, len(ids)))
            fresh = self.task.observe(self._state(ids), self._clip[ids], self._frame[ids])
            for k in obs:
                obs[k][ids] = fresh[k]
        return obs, reward.astype(np.float64), terminated, truncated, info

    def close_extras(self, **kwargs: Any) -> None:
        self.batch = None


def make_vector_env(num_envs: int = 1, **kwargs: Any) -> CrispTrackVectorEnv:
    """The ``vector_entry_point`` of ``CrispTrack-v0`` (gymnasium passes ``num_envs`` first)."""
    kwargs.pop("vectorization_mode", None)
    kwargs.pop("vector_kwargs", None)
    return CrispTrackVectorEnv(num_envs=num_envs, **kwargs)

