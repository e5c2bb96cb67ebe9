"""``CrispTrack-v0``: a humanoid tracks a reconstructed motion in its reconstructed scene."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields, replace
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from crisp_gym.envs import tracking
from crisp_gym.envs.config import TrackConfig, default_config
from crisp_gym.envs.library import ClipSource
from crisp_gym.envs.task import TrackingTask
from crisp_gym.render import EnvDisplay

_CONFIG_FIELDS = {f.name for f in fields(TrackConfig)}


def make_config(config: TrackConfig | None, overrides: dict[str, Any]) -> TrackConfig:
    """``config`` (or the default) with keyword overrides; unknown keywords are an error."""
    unknown = sorted(set(overrides) - _CONFIG_FIELDS)
    if unknown:
        # Python's own wording: wrappers such as TorchRL's GymEnv try an option (frameskip) and
        # fall back when the env answers with it
        raise TypeError(f"CrispTrack-v0 got an unexpected keyword argument {unknown[0]!r} (all unknown: {unknown}); "
                        f"valid ones are {sorted(_CONFIG_FIELDS)}")
    return replace(config or default_config(), **overrides)


class CrispTrackEnv(gym.Env):
    """Track a clip's reference motion with the 24-body humanoid in the clip's scene.

    The simulation runs at 120 Hz with ``implicitfast``; the policy acts at 30 Hz (4
    substeps). Every :class:`~crisp_gym.envs.config.TrackConfig` field is a keyword.

    ``clip`` is a clip name, a registry tag (``"bundled"``: every bundled clip), a clip
    directory, or a list of these: a *motion library* (:mod:`crisp_gym.envs.library`). Every
    reset then draws a clip (``clip_weights``) and a start frame (``start_sampling``:
    uniform or adaptive, :mod:`crisp_gym.envs.start_sampler`); observations mean the same
    whichever clip is tracked.

    ## Action space
    ``Box(-1, 1, (69,))``: PD targets of the 69 hinges, by default a residual on the next
    reference pose (``action_scale`` radians per unit); with ``residual_actions=False`` the
    action maps [-1, 1] onto each hinge's range. Hinges are in
    :data:`crisp_gym.humanoid.DOF_NAMES` order.

    ## Observation space
    ``Dict``, all float32, in the pelvis's heading frame:

    | key        | shape      | content                                                        |
    |------------|------------|----------------------------------------------------------------|
    | `proprio`  | (361,)     | root height; body positions, rotations (6D), linear and angular velocities |
    | `targets`  | (K, 432)   | per future reference frame and body: rotation difference, reference rotation, position difference, reference position relative to the root |
    | `points`   | (N, 3)     | scene surface points nearest the pelvis (only with `scene_aware=True`) |

    ## Reward
    The paper's six terms, each in ``info`` as ``reward_pos``, ``reward_rot``, ``reward_vel``,
    ``reward_ang_vel``, ``reward_height``, ``reward_energy``: position, rotation, linear
    and angular velocity, root height (``w·exp(-α·error)``) and an energy penalty
    ``-w_energy·Σ|τ·q̇|`` (``τ``: each hinge servo's torque, its clamped PD force and its damping).
    With ``w_root_pos > 0`` a seventh, ``reward_root_pos``: the pelvis's position alone,
    ``w_root_pos·exp(-a_root_pos·error)``, which still pulls back a body that has drifted.

    ## Episode end
    ``terminated`` when any body is more than ``termination_distance`` (0.5 m) from its
    reference, or when the simulation blows up (``info["unstable"]``: a state not finite, a hinge
    faster than ``max_joint_speed``, or MuJoCo resetting it for bad accelerations; the energy
    penalty counts at most ``max_power``, so rewards stay bounded); ``truncated`` at the clip's last frame, where
    ``info["success"]`` is ``True``. Starts use reference state init (10 % from frame 0);
    ``reset(options={"start_frame": k, "clip": c})`` picks the frame (and the clip, by index
    or name).

    ## Info
    ``clip`` (index into ``env.task.clip_names``), ``frame``, ``start_frame``,
    the six ``reward_*`` terms, ``max_body_error`` (m), ``farthest_body`` (the body it is measured
    on, index into ``crisp_gym.humanoid.BODY_NAMES``: on termination, the body that ended the episode),
    ``success``, ``unstable`` (the simulation
    blew up: see ``max_joint_speed``); the same keys after ``reset`` (terms 0, no success yet).
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 30}

    def __init__(self, clip: ClipSource | Sequence[ClipSource] = "flat_walk", scene_aware: bool = False,
                 render_mode: str | None = None, config: TrackConfig | None = None, **overrides: Any):
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}")
        self.config = make_config(config, {"scene_aware": scene_aware, **overrides})
        self.task = TrackingTask(clip, self.config)
        self.start_sampler = self.task.start_sampler()
        self.model = self.task.model
        self.data = mujoco.MjData(self.model)
        self.observation_space = self.task.observation_space()
        self.action_space = self.task.action_space()
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": self.config.control_hz}
        self._clip = np.zeros(1, dtype=int)
        self._frame = np.zeros(1, dtype=int)
        self._start_frame = 0
        self._display = EnvDisplay(self.model, render_mode, self.config.render_width, self.config.render_height)

    def _state(self):
        d = self.data
        return self.task.read_state(d.qpos[None], d.qvel[None], d.xpos[None], d.xquat[None], d.cvel[None],
                                    d.subtree_com[None], d.actuator_force[None], d.qfrc_damper[None])

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        forced = [self.task.clip_index(options["clip"])] if "clip" in options else None
        clips, frames = self.start_sampler.sample(self.np_random, 1, clips=forced)
        if "start_frame" in options:
            frames = np.array([int(options["start_frame"])])
        self.task.check_starts(clips, frames)
        self._clip, self._frame = clips, frames
        self._start_frame = int(frames[0])
        qpos, qvel, ctrl = self.task.reset_state(clips, frames)
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = qpos[0]
        self.data.qvel[:] = qvel[0]
        self.data.ctrl[:] = ctrl[0]
        mujoco.mj_step1(self.model, self.data)
        state = self._state()
        obs = self.task.observe(state, clips, frames)
        error, farthest = self.task.tracking_error(state, clips, frames)
        if self.render_mode == "human":
            self.render()
        return ({k: v[0] for k, v in obs.items()},
                {"clip": int(clips[0]), "frame": self._start_frame, "start_frame": self._start_frame,
                 **{f"reward_{name}": 0.0 for name in tracking.reward_term_names(self.config)},
                 "max_body_error": float(error[0]), "farthest_body": int(farthest[0]), "success": False,
                 "unstable": False})

    def step(self, action):
        next_frame = self._frame + 1
        self.data.ctrl[:] = self.task.controls(np.asarray(action)[None], self._clip, next_frame)[0]
        # step2/step1 split: the derived fields end at the new state, as the batch's mjSTAGE_VEL.
        # MuJoCo resets a simulation whose accelerations blow up (and counts it as a warning):
        # that episode ends as unstable, as the batch's failed simulations do.
        blowups = self.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number
        for _ in range(self.config.substeps):
            mujoco.mj_step2(self.model, self.data)
            mujoco.mj_step1(self.model, self.data)
        failed = self.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > blowups
        self._frame = next_frame
        state = self._state()
        reward, terms, terminated, truncated, error, farthest, unstable = self.task.evaluate(state, self._clip,
                                                                                           next_frame)
        unstable, terminated, truncated = unstable | failed, terminated | failed, truncated & ~failed
        obs = self.task.observe(state, self._clip, next_frame)
        if terminated[0] or truncated[0]:
            self.start_sampler.record(self._clip, next_frame, terminated)
        info = {"clip": int(self._clip[0]), "frame": int(next_frame[0]), "start_frame": self._start_frame,
                **{k: float(v[0]) for k, v in tracking.reward_info(terms).items()},
                "max_body_error": float(error[0]), "farthest_body": int(farthest[0]), "success": bool(truncated[0]),
                "unstable": bool(unstable[0])}
        if self.render_mode == "human":
            self.render()
        return ({k: v[0] for k, v in obs.items()}, float(reward[0]), bool(terminated[0]),
                bool(truncated[0]), info)

    def render(self):
        """``rgb_array``: the frame from the ``follow`` camera; ``human``: MuJoCo's viewer shows the
        state (called by ``reset`` and ``step`` themselves, as gymnasium's human mode does)."""
        return self._display.show(self.data)

    def close(self):
        self._display.close()
