"""The tracking task over a motion library: the composed model, the references and the spaces.

Shared by the single and the batched env; it owns no simulation state. Every per-simulation
method takes the simulations' clip indices and frames (frame numbers of their own clips).
"""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium as gym
import numpy as np

from crisp_gym.envs import tracking
from crisp_gym.envs.config import TrackConfig
from crisp_gym.envs.library import ClipSource, MotionLibrary
from crisp_gym.envs.start_sampler import StartSampler
from crisp_gym.humanoid import hinge_ranges


class TrackingTask:
    """Everything about tracking a library of clips that does not change during an episode.

    Args:
        clip: one clip source or several (names, registry tags, directories, loaded clips).
        config: the env config.
    """

    def __init__(self, clip: ClipSource | Sequence[ClipSource], config: TrackConfig):
        self.config = config
        self.library = MotionLibrary(clip, config)
        self.model = self.library.model
        self.body_ids = self.library.body_ids
        self.reference = self.library.reference
        self.ranges = hinge_ranges()
        self.damping_lead = tracking.damping_lead(self.model)
        if config.clip_weights is not None and len(config.clip_weights) != self.library.num_clips:
            raise ValueError(f"clip_weights has {len(config.clip_weights)} entries for "
                             f"{self.library.num_clips} clips {self.library.names}")

    @property
    def clip_names(self) -> list[str]:
        return self.library.names

    @property
    def num_frames(self) -> np.ndarray:
        """(C,) frames of each clip at the control rate."""
        return self.library.num_frames

    def observation_space(self) -> gym.spaces.Dict:
        cfg = self.config
        spaces = {
            "proprio": gym.spaces.Box(-np.inf, np.inf, (tracking.PROPRIO_DIM,), np.float32),
            "targets": gym.spaces.Box(-np.inf, np.inf, (cfg.num_future_frames, tracking.TARGET_DIM), np.float32),
        }
        if cfg.scene_aware:
            spaces["points"] = gym.spaces.Box(-np.inf, np.inf, (cfg.num_points, 3), np.float32)
        return gym.spaces.Dict(spaces)

    def action_space(self) -> gym.spaces.Box:
        return gym.spaces.Box(-1.0, 1.0, (self.model.nu,), np.float32)

    def start_sampler(self) -> StartSampler:
        """A fresh start-frame sampler for this library (one per env: adaptive ones keep counts)."""
        return StartSampler(self.num_frames, self.config)

    def clip_index(self, clip: int | str) -> int:
        """The library index of a clip given by index or name."""
        if isinstance(clip, (int, np.integer)) and 0 <= clip < self.library.num_clips:
            return int(clip)
        if isinstance(clip, str) and clip in self.library.names:
            return self.library.names.index(clip)
        raise ValueError(f"clip must be an index below {self.library.num_clips} or one of {self.library.names}, "
                         f"got {clip!r}")

    def check_starts(self, clips: np.ndarray, frames: np.ndarray) -> None:
        """Raise unless every frame can start an episode of its clip (any frame but the last)."""
        bad = (frames < 0) | (frames >= self.num_frames[clips] - 1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"start_frame must be in [0, {self.num_frames[clips[i]] - 2}] for clip "
                             f"{self.library.names[clips[i]]!r}, got {int(frames[i])}")

    def reset_state(self, clips: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, nq) qpos, (N, nv) qvel and (N, nu) PD targets of the reference at ``frames``."""
        rows = self.library.global_frames(clips, frames)
        ref = self.reference
        return ref.qpos[rows].copy(), ref.qvel[rows].copy(), ref.dof_pos[rows].copy()

    def observe(self, state: tracking.SimState, clips: np.ndarray, frames: np.ndarray) -> dict[str, np.ndarray]:
        """Batched observation dict, float32."""
        cfg = self.config
        rows = self.library.global_frames(clips, frames)
        future = tracking.future_frames(rows, cfg.num_future_frames, self.library.last_frames(clips))
        obs = {
            "proprio": tracking.proprioception(state),
            "targets": tracking.target_features(state, self.reference, future),
        }
        if cfg.scene_aware:
            points = np.empty((len(rows), cfg.num_points, 3))
            for clip in np.unique(clips):
                sims = np.flatnonzero(clips == clip)
                points[sims] = tracking.nearest_points(state.body_pos[sims, 0], state.body_quat[sims, 0],
                                                       self.library.point_trees[clip], cfg.num_points)
            obs["points"] = points
        return {k: v.astype(np.float32) for k, v in obs.items()}

    def tracking_error(self, state: tracking.SimState, clips: np.ndarray,
                       frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) largest distance (m) of any body from its reference, and (N,) which body (index in
        ``BODY_NAMES``)."""
        return tracking.farthest_body(state, self.reference, self.library.global_frames(clips, frames))

    def evaluate(self, state: tracking.SimState, clips: np.ndarray, frames: np.ndarray):
        """Reward, its terms, termination, truncation (end of clip), the tracking error and the body
        farthest from its reference, and whether the simulation is blowing up (a state not finite,
        or a hinge faster than ``max_joint_speed``)."""
        rows = self.library.global_frames(clips, frames)
        terms = tracking.reward_terms(state, self.reference, rows, self.config)
        reward = sum(terms.values())
        error, farthest = tracking.farthest_body(state, self.reference, rows)
        finite = np.isfinite(state.qpos).all(axis=1) & np.isfinite(state.qvel).all(axis=1)
        with np.errstate(invalid="ignore"):
            unstable = ~finite | (np.abs(state.qvel[:, 6:]).max(axis=1) > self.config.max_joint_speed)
        terminated = (error > self.config.termination_distance) | unstable
        truncated = (frames >= self.num_frames[clips] - 1) & ~terminated
        return np.where(finite, reward, 0.0), terms, terminated, truncated, error, farthest, unstable

    def controls(self, action: np.ndarray, clips: np.ndarray, next_frames: np.ndarray) -> np.ndarray:
        action = np.asarray(action, dtype=float)
        if action.shape[-1] != self.model.nu or not np.all(np.isfinite(action)):
            raise ValueError(f"actions must be finite with {self.model.nu} entries, got shape {action.shape}")
        rows = self.library.global_frames(clips, next_frames)
        return tracking.pd_targets(action, self.reference, rows, self.config, self.ranges, self.damping_lead)

    def read_state(self, qpos, qvel, xpos, xquat, cvel, subtree_com, actuator_force,
                   qfrc_damper) -> tracking.SimState:
        return tracking.sim_state(qpos, qvel, xpos, xquat, cvel, subtree_com, actuator_force, qfrc_damper,
                                  self.body_ids)

