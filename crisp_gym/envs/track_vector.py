"""The batched ``CrispTrack-v0``: all simulations stepped by one ``mujoco.batch.Batch`` call.

``gym.make_vec("CrispTrack-v0", num_envs=N, vectorization_mode="vector_entry_point", ...)``
returns it. Stepping releases the GIL inside MuJoCo's thread pool; a persistent batch keeps
one MjData per simulation, and ``stage=mjSTAGE_VEL`` leaves the derived fields at the new
state at no extra cost, which is what the observation reads.

Autoreset (``autoreset_mode``) is ``SAME_STEP`` by default: a finished simulation is reset inside
the same ``step``; the returned observation starts its next episode, and ``info["final_obs"]`` /
``info["final_info"]`` (masked by ``info["_final_obs"]``) hold the last one. TorchRL needs this
mode. ``"next_step"`` is gymnasium's own default, which its vector wrappers
(``NormalizeObservation``, ``FlattenObservation``, ...) require: a finished simulation returns its
last observation, and the next ``step`` resets it instead of stepping (its action is ignored;
reward 0, neither terminated nor truncated).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import mujoco.batch
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from threadpoolctl import ThreadpoolController

from crisp_gym.envs.config import TrackConfig
from crisp_gym.envs.library import ClipSource
from crisp_gym.envs.task import TrackingTask
from crisp_gym.envs.track import make_config
from crisp_gym.envs.tracking import reward_info, reward_term_names
from crisp_gym.render import EnvDisplay

_BOUND_FIELDS = ("qpos", "qvel", "ctrl", "xpos", "xquat", "cvel", "subtree_com", "actuator_force", "qfrc_damper")
# What a new episode writes besides qpos, qvel and ctrl: the rest of MuJoCo's integration state
# and the applied forces, all zero after mj_resetData (the env moves no mocap body, and its
# composed models have no plugins).
_RESET_FIELDS = ("time", "act", "qacc_warmstart", "qfrc_applied", "xfrc_applied")
_SNAPSHOT_FIELDS = ("qpos", "qvel", "ctrl", *_RESET_FIELDS)  # what the next step depends on


def _on_one_blas_thread(method: Callable) -> Callable:
    """Run an env method with numpy's BLAS on one thread (the caller's setting back afterwards).

    After a threaded product OpenBLAS's idle workers keep spinning and take cores from the MuJoCo
    threads stepping next (docs/benchmarks.md: 1.5x the env steps/s on a 2-core machine).
    """

    @functools.wraps(method)
    def limited(self: CrispTrackVectorEnv, *args: Any, **kwargs: Any) -> Any:
        with self._blas.limit(limits=1):
            return method(self, *args, **kwargs)

    return limited


@dataclass(frozen=True)
class EnvSnapshot:
    """Copies of simulations' whole states, from :meth:`CrispTrackVectorEnv.snapshot`.

    Attributes:
        physics: MuJoCo's integration state per simulation (``qpos``, ``qvel``, ``ctrl``, the
            solver's warm start, ...), one row each.
        clip, frame, start_frame: (N,) where each simulation is in its episode.
    """

    physics: dict[str, np.ndarray]
    clip: np.ndarray
    frame: np.ndarray
    start_frame: np.ndarray

    def __len__(self) -> int:
        return len(self.clip)


class StartObservations:
    """The observations of simulations just reset, kept per reference row (clip and frame).

    A reset writes the reference's state (and zeros the rest of the integration state) into a
    simulation of the batch's one model, and the observation reads only positions and
    velocities: so a start's observation is the same every time, bit for bit. Each row is
    computed by the env's own path the first time a simulation starts there; arrays for all
    rows are reserved up front, and the memory of a row is touched only once it is filled.
    """

    def __init__(self, spaces: dict[str, Any], num_rows: int):
        self.table = {k: np.empty((num_rows, *space.shape), dtype=space.dtype) for k, space in spaces.items()}
        self.known = np.zeros(num_rows, dtype=bool)

    def missing(self, rows: np.ndarray) -> np.ndarray:
        """A mask over ``rows``: those not kept yet."""
        return ~self.known[rows]

    def keep(self, rows: np.ndarray, obs: dict[str, np.ndarray]) -> None:
        for k, v in obs.items():
            self.table[k][rows] = v
        self.known[rows] = True

    def __getitem__(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        return {k: v[rows] for k, v in self.table.items()}


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
        autoreset_mode: ``"same_step"`` (default) or ``"next_step"`` (or the ``AutoresetMode``);
            see the module docstring.
        render_mode: ``"rgb_array"``: ``render()`` returns one image per simulation (a tuple, as
            gymnasium's vector envs do), each from its ``follow`` camera; ``"human"``: MuJoCo's
            viewer shows the first simulation, synced on every ``reset`` and ``step``.
        config, **overrides: as for the single env.

    ``reset(options={"start_frame": frames, "clip": clips})`` fixes the start frames and/or
    clips (scalars or one per simulation).
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 30, "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int = 1, clip: ClipSource | Sequence[ClipSource] = "flat_walk",
                 scene_aware: bool = False, num_threads: int = 0,
                 autoreset_mode: str | AutoresetMode = AutoresetMode.SAME_STEP, config: TrackConfig | None = None,
                 render_mode: str | None = None, **overrides: Any):
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}")
        self.render_mode = render_mode
        self.config = make_config(config, {"scene_aware": scene_aware, **overrides})
        self.task = TrackingTask(clip, self.config)
        self.start_sampler = self.task.start_sampler()
        self.model = self.task.model
        self.num_envs = num_envs
        modes = {"same_step": AutoresetMode.SAME_STEP, "next_step": AutoresetMode.NEXT_STEP}
        mode = autoreset_mode.name.lower() if isinstance(autoreset_mode, AutoresetMode) else str(autoreset_mode)
        if mode not in modes:
            raise ValueError(f"autoreset_mode must be one of {sorted(modes)}, got {autoreset_mode!r}")
        self.autoreset_mode = modes[mode]
        self.metadata = {**self.metadata, "autoreset_mode": self.autoreset_mode, "render_fps": self.config.control_hz}
        self._needs_reset = np.zeros(num_envs, dtype=bool)  # NEXT_STEP: finished on the previous step
        self.batch = mujoco.batch.Batch(self.model, num_envs, nthread=num_threads, persistent=True)
        self._blas = ThreadpoolController().select(user_api="blas")  # see _on_one_blas_thread
        self._fields = {name: self.batch.bind(name) for name in _BOUND_FIELDS + _RESET_FIELDS}
        self.single_observation_space = self.task.observation_space()
        self.single_action_space = self.task.action_space()
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._clip = np.zeros(num_envs, dtype=int)
        self._frame = np.zeros(num_envs, dtype=int)
        self._start_frame = np.zeros(num_envs, dtype=int)
        self._all = np.arange(num_envs)
        self._start_obs = StartObservations(dict(self.single_observation_space.spaces),
                                            len(self.task.reference.qpos))
        self._scratch = mujoco.MjData(self.model)  # one simulation's state, for drawing it
        self._display = EnvDisplay(self.model, render_mode, self.config.render_width, self.config.render_height)

    def _state(self, ids: np.ndarray | slice = slice(None)):
        f = {name: self._fields[name][ids] for name in _BOUND_FIELDS if name != "ctrl"}
        return self.task.read_state(f["qpos"], f["qvel"], f["xpos"], f["xquat"], f["cvel"], f["subtree_com"],
                                    f["actuator_force"], f["qfrc_damper"])

    def _reset_sims(self, ids: np.ndarray, clips: np.ndarray, frames: np.ndarray) -> None:
        qpos, qvel, ctrl = self.task.reset_state(clips, frames)
        # The state written field by field: mj_resetData would clear each simulation's whole
        # MjData, its arena included, which made up most of a reset's time after a step.
        for name in _RESET_FIELDS:
            self._fields[name][ids] = 0.0
        self._fields["qpos"][ids] = qpos
        self._fields["qvel"][ids] = qvel
        self._fields["ctrl"][ids] = ctrl
        # No forward pass here: a step computes its own from qpos and qvel, so only the simulations
        # whose derived fields are read before their next step need one (see _forward).
        self._clip[ids] = clips
        self._frame[ids] = frames
        self._start_frame[ids] = frames

    def _forward(self, ids: np.ndarray) -> None:
        """Bring the derived fields (body poses, velocities, forces) of simulations just reset up
        to their new state, for reading them before their next step."""
        self.batch.forward(np.unique(ids), stage=mujoco.mjtStage.mjSTAGE_VEL)  # the batch takes sorted ids

    def _start_observation(self, ids: np.ndarray) -> dict[str, np.ndarray]:
        """The observations of simulations ``ids``, just reset (see :class:`StartObservations`)."""
        rows = self.task.library.global_frames(self._clip[ids], self._frame[ids])
        new = self._start_obs.missing(rows)
        if new.any():
            fresh = ids[new]
            rows_new, first = np.unique(rows[new], return_index=True)  # two starts at one frame: once
            self._forward(fresh[first])
            obs = self.task.observe(self._state(fresh[first]), self._clip[fresh[first]], self._frame[fresh[first]])
            self._start_obs.keep(rows_new, obs)
        return self._start_obs[rows]

    def snapshot(self, ids: np.ndarray | None = None) -> EnvSnapshot:
        """The states of simulations ``ids`` (all by default), for :meth:`restore`."""
        ids = self._all if ids is None else np.asarray(ids, dtype=int)
        return EnvSnapshot({name: self._fields[name][ids].copy() for name in _SNAPSHOT_FIELDS},
                           self._clip[ids].copy(), self._frame[ids].copy(), self._start_frame[ids].copy())

    @_on_one_blas_thread
    def restore(self, snapshot: EnvSnapshot, rows: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Simulation ``i`` continues from row ``rows[i]`` of ``snapshot`` (default: row ``i``),
        exactly as the simulation it was taken from would have; returns the observations.

        One state may go to several simulations (a search branching from it). The start sampler's
        counts are not touched: episodes restored this way are not the sampler's draws.
        """
        rows = np.arange(self.num_envs) if rows is None else np.asarray(rows, dtype=int)
        if rows.shape != (self.num_envs,) or rows.min() < 0 or rows.max() >= len(snapshot):
            raise ValueError(f"rows must give one of the snapshot's {len(snapshot)} states to each of the "
                             f"{self.num_envs} simulations, got shape {rows.shape}")
        for name, value in snapshot.physics.items():
            self._fields[name][:] = value[rows]
        self._clip[:], self._frame[:], self._start_frame[:] = (snapshot.clip[rows], snapshot.frame[rows],
                                                               snapshot.start_frame[rows])
        self._needs_reset[:] = False
        self._forward(self._all)
        return self.task.observe(self._state(), self._clip, self._frame)

    @_on_one_blas_thread
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
        self._forward(self._all)
        self._needs_reset[:] = False
        obs = self._start_observation(self._all)
        error, farthest = self.task.tracking_error(self._state(), self._clip, self._frame)
        # The same keys as a step's info (terms zero, no success yet): wrappers that read infos
        # into fixed specs, e.g. TorchRL's GymWrapper, need them on every call.
        terms = reward_info({name: np.zeros(self.num_envs) for name in reward_term_names(self.config)})
        if self.render_mode == "human":
            self.render()
        return obs, {"clip": self._clip.copy(), "frame": self._frame.copy(), "start_frame": self._start_frame.copy(),
                     **terms, "max_body_error": error, "farthest_body": farthest,
                     "success": np.zeros(self.num_envs, dtype=bool),
                     "unstable": np.zeros(self.num_envs, dtype=bool)}

    def step(self, actions):
        result = self._step(actions)
        if self.render_mode == "human":
            self.render()
        return result

    @_on_one_blas_thread
    def _step(self, actions):
        # NEXT_STEP: a simulation reset by this step does not advance past its clip's end.
        next_frame = self._frame + ~self._needs_reset
        self._fields["ctrl"][:] = self.task.controls(np.asarray(actions).reshape(self.num_envs, -1), self._clip,
                                                     next_frame)
        try:
            self.batch.step(nstep=self.config.substeps, stage=mujoco.mjtStage.mjSTAGE_VEL)
            failed = np.zeros(self.num_envs, dtype=bool)
        except mujoco.batch.SimulationError as err:  # the others ran on; end the failed episodes
            failed = np.isin(self._all, err.ids)
        self._frame = next_frame
        state = self._state()
        reward, terms, terminated, truncated, error, farthest, unstable = self.task.evaluate(state, self._clip,
                                                                                           next_frame)
        unstable = unstable | failed
        terminated = terminated | failed
        truncated = truncated & ~failed
        obs = self.task.observe(state, self._clip, next_frame)
        info: dict[str, Any] = {"clip": self._clip.copy(), "frame": next_frame.copy(),
                                "start_frame": self._start_frame.copy(), **reward_info(terms),
                                "max_body_error": error, "farthest_body": farthest, "success": truncated.copy(),
                                "unstable": unstable}
        done = terminated | truncated
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            return self._next_step_autoreset(obs, reward, terminated, truncated, info)
        if done.any():
            ids = np.flatnonzero(done)
            self.start_sampler.record(self._clip[ids], next_frame[ids], terminated[ids])
            info["final_obs"] = np.array([None] * self.num_envs, dtype=object)
            info["final_info"] = np.array([None] * self.num_envs, dtype=object)
            last = {k: v[ids] for k, v in obs.items()}  # copies: the reset rows of obs are overwritten below
            for j, i in enumerate(ids):
                info["final_obs"][i] = {k: v[j] for k, v in last.items()}
                info["final_info"][i] = {"clip": int(self._clip[i]), "frame": int(next_frame[i]),
                                         "start_frame": int(self._start_frame[i]),
                                         "max_body_error": float(error[i]), "farthest_body": int(farthest[i]),
                                         "success": bool(truncated[i]), "unstable": bool(unstable[i])}
            info["_final_obs"] = done.copy()
            info["_final_info"] = done.copy()
            self._reset_sims(ids, *self.start_sampler.sample(self.np_random, len(ids)))
            fresh = self._start_observation(ids)
            for k in obs:
                obs[k][ids] = fresh[k]
        return obs, reward.astype(np.float64), terminated, truncated, info

    def _next_step_autoreset(self, obs, reward, terminated, truncated, info):
        """NEXT_STEP: the simulations that finished on the previous step start over now (their
        physics step is discarded); those finishing now keep their last observation."""
        starting = self._needs_reset
        finished = (terminated | truncated) & ~starting
        if finished.any():
            ids = np.flatnonzero(finished)
            self.start_sampler.record(self._clip[ids], self._frame[ids], terminated[ids])
        if starting.any():
            ids = np.flatnonzero(starting)
            self._reset_sims(ids, *self.start_sampler.sample(self.np_random, len(ids)))
            fresh = self._start_observation(ids)
            for k in obs:
                obs[k][ids] = fresh[k]
            reward[ids] = 0.0
            terminated[ids] = truncated[ids] = info["success"][ids] = info["unstable"][ids] = False
            for name in reward_term_names(self.config):
                info[f"reward_{name}"][ids] = 0.0
            info["clip"][ids], info["frame"][ids] = self._clip[ids], self._frame[ids]
            info["start_frame"][ids] = self._start_frame[ids]
            self._forward(ids)
            info["max_body_error"][ids], info["farthest_body"][ids] = self.task.tracking_error(
                self._state(ids), self._clip[ids], self._frame[ids])
        self._needs_reset = finished
        return obs, reward.astype(np.float64), terminated, truncated, info

    def render(self) -> tuple[np.ndarray, ...] | None:
        """See ``render_mode`` in the class docstring."""
        if self.render_mode is None:
            return None
        images = []
        for k in range(1 if self.render_mode == "human" else self.num_envs):
            self._scratch.qpos[:], self._scratch.qvel[:] = self._fields["qpos"][k], self._fields["qvel"][k]
            mujoco.mj_forward(self.model, self._scratch)
            images.append(self._display.show(self._scratch))
        return None if self.render_mode == "human" else tuple(images)

    def close_extras(self, **kwargs: Any) -> None:
        self._display.close()
        self.batch = None


def make_vector_env(num_envs: int = 1, **kwargs: Any) -> CrispTrackVectorEnv:
    """The ``vector_entry_point`` of ``CrispTrack-v0`` (gymnasium passes ``num_envs`` first)."""
    kwargs.pop("vectorization_mode", None)
    kwargs.pop("vector_kwargs", None)
    return CrispTrackVectorEnv(num_envs=num_envs, **kwargs)

