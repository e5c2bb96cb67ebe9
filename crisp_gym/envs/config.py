"""Configuration of the tracking env; the defaults are the paper's values (Sec. 3.4)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrackConfig:
    """Every knob of ``CrispTrack-v0``; pass any field as a keyword to ``gym.make``.

    Attributes:
        sim_hz: physics rate (the humanoid model's timestep must match).
        control_hz: policy rate; ``sim_hz / control_hz`` substeps per action.
        residual_actions: PD targets are the next reference pose plus ``action_scale`` × action
            (default); otherwise the action in [-1, 1] maps onto each hinge's range.
        action_scale: radians per unit action in residual mode.
        velocity_feedforward: in residual mode, each PD target also leads the reference by
            ``kd / kp`` times the reference's hinge velocity, so that the servo's damping acts on
            the velocity error instead of on the velocity. Without the lead a servo lags a
            moving reference by ``kd / kp`` seconds (0.1 s with the humanoid's gains): 1 rad at
            10 rad/s, the whole residual range, which fast captured moves (kicks, arm throws)
            exceed. The shipped policies were trained without it.
        max_feedforward_lead: the lead is clipped to ±this (rad). Captured motion's light
            bodies turn at up to ~1,500 °/s for a frame or two (CMU 131_01's right ankle and upper
            arm); on the servos that damped inside their clamp an unclipped lead of 2+ rad flipped
            the foot, while most of the lag is removed within ±0.3 rad (``docs/training.md``).
        num_future_frames: K, the reference frames in the ``targets`` observation.
        scene_aware: add the ``points`` observation (surface points of nearby primitives).
        num_points: N, points in the ``points`` observation.
        point_spacing: grid spacing (m) of the scene surface samples the points are drawn from.
        point_radius: scene samples farther than this (m) from the motion's pelvis path are
            never observed (keeps the candidate set small).
        w_pos, w_rot, w_vel, w_ang_vel, w_height, w_energy: reward weights; the energy term
            enters with a negative sign (a penalty).
        a_pos, a_rot, a_vel, a_ang_vel, a_height: reward sharpness; each norm is the sum over
            the 24 bodies of the per-body Euclidean error (m, rad, m/s, rad/s; the root height
            error in m).
        w_root_pos, a_root_pos: an optional seventh term (off at weight 0, the paper's reward),
            ``w_root_pos * exp(-a_root_pos * |pelvis error|)`` (m): the position term sums 24
            bodies' errors, so a pelvis drifted 0.2 m leaves it under 0.1 % of its weight and no
            pull back; this one still gives 55 % at 0.2 m (``info["reward_root_pos"]``).
        termination_distance: early termination when any body is farther than this (m)
            from its reference.
        max_joint_speed: rad/s; a hinge turning faster is a simulation blowing up (people's
            fastest joints turn at about 30): the episode terminates, ``info["unstable"]``.
        max_power: W; the energy term's penalty counts at most this much actuator power, so a
            blowing-up step's reward stays bounded (people deliver a few kW at most).
        rsi_first_frame_prob: reference state init from frame 0 with this probability, else
            from a uniformly drawn frame.
        random_start: ``False`` always starts at frame 0 (evaluation).
        start_sampling: ``"uniform"`` (reference state init: any frame equally likely) or
            ``"adaptive"`` (frames drawn in proportion to recent failures, mixed with uniform;
            see :mod:`crisp_gym.envs.start_sampler`).
        clip_weights: with several clips, the relative probability of drawing each one at a
            reset, in library order (``None``: equal).
        clip_sampling: ``"fixed"`` (clips drawn by ``clip_weights``) or ``"adaptive"`` (mixed
            with each clip's weight times its recent failure rate; see
            :mod:`crisp_gym.envs.start_sampler`).
        adaptive_bin_seconds: length of the time bins failures are counted in.
        adaptive_uniform_share: share of adaptive starts drawn uniformly instead (and of
            adaptive clip draws made by ``clip_weights`` alone).
        adaptive_memory: ended episodes over which failure counts are forgotten (by 1/e).
        adaptive_lookback: bins before a failure whose probability it also raises.
        adaptive_lookback_decay: weight of each bin further back (1, d, d², ...).
        render_width, render_height: ``rgb_array`` frame size.
    """

    sim_hz: float = 120.0
    control_hz: float = 30.0
    residual_actions: bool = True
    action_scale: float = 1.0
    velocity_feedforward: bool = False
    max_feedforward_lead: float = 0.3
    num_future_frames: int = 5
    scene_aware: bool = False
    num_points: int = 128
    point_spacing: float = 0.1
    point_radius: float = 2.5
    w_pos: float = 2.5
    w_rot: float = 1.5
    w_vel: float = 0.5
    w_ang_vel: float = 0.5
    w_height: float = 1.0
    w_energy: float = 0.001
    a_pos: float = 1.5
    a_rot: float = 0.3
    a_vel: float = 0.12
    a_ang_vel: float = 0.05
    a_height: float = 20.0
    w_root_pos: float = 0.0
    a_root_pos: float = 3.0
    termination_distance: float = 0.5
    max_joint_speed: float = 50.0
    max_power: float = 1.0e4
    rsi_first_frame_prob: float = 0.1
    random_start: bool = True
    start_sampling: str = "uniform"
    clip_weights: tuple[float, ...] | None = None
    clip_sampling: str = "fixed"
    adaptive_bin_seconds: float = 1.0
    adaptive_uniform_share: float = 0.2
    adaptive_memory: float = 500.0
    adaptive_lookback: int = 2
    adaptive_lookback_decay: float = 0.5
    render_width: int = 640
    render_height: int = 480

    def __post_init__(self) -> None:
        substeps = self.sim_hz / self.control_hz
        if self.sim_hz <= 0 or self.control_hz <= 0 or abs(substeps - round(substeps)) > 1e-9:
            raise ValueError(f"sim_hz ({self.sim_hz}) must be a positive multiple of control_hz "
                             f"({self.control_hz})")
        if self.num_future_frames < 1 or self.num_points < 1:
            raise ValueError("num_future_frames and num_points must be at least 1")
        if not (self.w_root_pos >= 0 and self.a_root_pos > 0):
            raise ValueError(f"w_root_pos must be non-negative and a_root_pos positive, got {self.w_root_pos}, "
                             f"{self.a_root_pos}")
        if not 0.0 <= self.rsi_first_frame_prob <= 1.0:
            raise ValueError(f"rsi_first_frame_prob must be in [0, 1], got {self.rsi_first_frame_prob}")
        if min(self.termination_distance, self.action_scale, self.point_spacing, self.max_joint_speed,
               self.max_power, self.max_feedforward_lead) <= 0:
            raise ValueError("termination_distance, action_scale, point_spacing, max_joint_speed, max_power and "
                             "max_feedforward_lead must be positive")

        if self.start_sampling not in ("uniform", "adaptive"):
            raise ValueError(f"start_sampling must be 'uniform' or 'adaptive', got {self.start_sampling!r}")
        if self.clip_sampling not in ("fixed", "adaptive"):
            raise ValueError(f"clip_sampling must be 'fixed' or 'adaptive', got {self.clip_sampling!r}")
        if self.clip_weights is not None:
            weights = np.asarray(self.clip_weights, dtype=float)
            if weights.ndim != 1 or not np.all(np.isfinite(weights)) or weights.min() < 0 or weights.sum() <= 0:
                raise ValueError(f"clip_weights must be non-negative numbers, not all zero, got {self.clip_weights}")
            object.__setattr__(self, "clip_weights", tuple(float(w) for w in weights))
        if not (self.adaptive_bin_seconds > 0 and self.adaptive_memory > 0 and 0 <= self.adaptive_uniform_share <= 1
                and self.adaptive_lookback >= 0 and 0 <= self.adaptive_lookback_decay <= 1):
            raise ValueError("adaptive_bin_seconds and adaptive_memory must be positive, adaptive_uniform_share and "
                             "adaptive_lookback_decay in [0, 1], adaptive_lookback non-negative")

    @property
    def substeps(self) -> int:
        return int(round(self.sim_hz / self.control_hz))


def default_config() -> TrackConfig:
    """The paper's configuration of the tracking env."""
    return TrackConfig()
