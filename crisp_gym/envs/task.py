"""One clip's tracking task: the composed model, the reference and the spaces.

Shared by the single and the batched env; it owns no simulation state.
"""

from __future__ import annotations

import os

import gymnasium as gym
import mujoco
import numpy as np
from scipy.spatial import cKDTree

from crisp_gym.clip import Clip
from crisp_gym.envs import tracking
from crisp_gym.envs.config import TrackConfig
from crisp_gym.mjcf_scene import scene_surface
from crisp_gym.motion import humanoid_body_ids, humanoid_qpos_adr
from crisp_gym.registry import load_clip


class TrackingTask:
    """Everything about tracking one clip that does not change during an episode."""

    def __init__(self, clip: str | os.PathLike | Clip, config: TrackConfig):
        self.clip = clip if isinstance(clip, Clip) else load_clip(clip)
        self.config = config
        # Box scenes come from their primitives; other scenes bring their geometry in scene.xml.
        scene_xml = None if self.clip.scene_kind == "boxes" else self.clip.scene_xml
        self.model = tracking.build_track_model(self.clip.boxes, timestep=1.0 / config.sim_hz, scene_xml=scene_xml)
        if humanoid_qpos_adr(self.model) != 0:
            raise ValueError("the humanoid's free joint must come first in the composed model")
        self.body_ids = humanoid_body_ids(self.model)
        self.reference = tracking.Reference.from_motion(self.clip.motion, self.model, config.control_hz)
        self.ranges = tracking.hinge_ranges()
        self.points = None
        if config.scene_aware:
            self.points = (tracking.scene_samples(self.clip.boxes, self.reference, config) if scene_xml is None
                           else tracking.mesh_scene_samples(scene_surface(scene_xml), self.reference, config))
        if self.points is not None and len(self.points) == 0:
            raise ValueError("scene_aware=True but the scene has no surface within point_radius of the motion")
        self.point_tree = cKDTree(self.points) if self.points is not None else None

    @property
    def num_frames(self) -> int:
        return self.reference.num_frames

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

    def sample_start_frames(self, rng: np.random.Generator, count: int) -> np.ndarray:
        return tracking.sample_start_frames(rng, count, self.num_frames, self.config)

    def reset_state(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, nq) qpos and (N, nv) qvel of the reference at ``frames``."""
        return self.reference.qpos[frames].copy(), self.reference.qvel[frames].copy()

    def observe(self, state: tracking.SimState, frame: np.ndarray) -> dict[str, np.ndarray]:
        """Batched observation dict, float32."""
        cfg = self.config
        obs = {
            "proprio": tracking.proprioception(state),
            "targets": tracking.target_features(
                state, self.reference, tracking.future_frames(frame, cfg.num_future_frames, self.num_frames)),
        }
        if cfg.scene_aware:
            obs["points"] = tracking.nearest_points(state, self.point_tree, cfg.num_points)
        return {k: v.astype(np.float32) for k, v in obs.items()}

    def evaluate(self, state: tracking.SimState, frame: np.ndarray):
        """Reward, its terms, termination, truncation (end of clip) and the tracking error."""
        terms = tracking.reward_terms(state, self.reference, frame, self.config)
        reward = sum(terms.values())
        error = tracking.max_body_error(state, self.reference, frame)
        finite = np.isfinite(state.qpos).all(axis=1) & np.isfinite(state.qvel).all(axis=1)
        terminated = (error > self.config.termination_distance) | ~finite
        truncated = (frame >= self.num_frames - 1) & ~terminated
        return np.where(finite, reward, 0.0), terms, terminated, truncated, error

    def controls(self, action: np.ndarray, next_frame: np.ndarray) -> np.ndarray:
        action = np.asarray(action, dtype=float)
        if action.shape[-1] != self.model.nu or not np.all(np.isfinite(action)):
            raise ValueError(f"actions must be finite with {self.model.nu} entries, got shape {action.shape}")
        return tracking.pd_targets(action, self.reference, next_frame, self.config, self.ranges)

    def read_state(self, qpos, qvel, xpos, xquat, cvel, subtree_com, actuator_force) -> tracking.SimState:
        return tracking.sim_state(qpos, qvel, xpos, xquat, cvel, subtree_com, actuator_force, self.body_ids)


def forward_velocity_stage(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    """Position- and velocity-dependent quantities at the current state (as mjSTAGE_VEL)."""
    mujoco.mj_fwdPosition(model, data)
    mujoco.mj_fwdVelocity(model, data)
