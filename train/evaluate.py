"""Evaluation of a tracking policy: success, world-frame tracking errors, smoothness, plots, video.

``crisp eval RUN_OR_CHECKPOINT [--clip NAME] [-o OUT] [--episodes N] [--video/--no-video]``
rolls the policy's mean action (no exploration noise) out in ``CrispTrack-v0`` twice:

* **RSI starts**: ``--episodes`` episodes in one batched env, from start frames drawn as in
  training (reference state init: 10 % frame 0, else uniform); the success rate and the
  rollout throughput (FPS, env-steps per second including the policy) come from these;
* **from frame 0**: one episode over the whole clip in the single env (deterministic, so one
  is enough). The tracking metrics, the plots and the video come from it.

Metrics (paper, Sec. 4, after WHAM/TRAM), over the 24 body origins (the joints) of the
simulated humanoid against the reference (positions in metres, errors in millimetres):

* ``w_mpjpe_mm``: W-MPJPE₁₀₀, the clip split into 100-frame segments, each rigidly aligned
  (rotation + translation) to the reference on its first two frames;
* ``wa_mpjpe_mm``: WA-MPJPE₁₀₀, each segment rigidly aligned on all its frames (Procrustes
  without scale: both motions are metric, so a scale would only hide errors);
* ``mpjpe_mm``: no alignment (the simulation and the reference share the world frame);
* ``jitter_m_s3``: mean norm of the joints' jerk (third finite difference × fps³), for the
  rollout and, as ``reference_jitter_m_s3``, the reference (the paper's tables divide by 10);
* ``accel_error_mm_frame2``: mean norm of the difference of the joints' second finite
  differences (mm/frame², the HMR literature's unit).

Outputs in ``-o``: ``report.html`` (the page to open), ``report.json``, ``tracking.png``
(largest body error and reward terms over time), ``torques.png`` (actuator torques by body
group) and ``rollout.mp4`` (the simulated humanoid with its reference as a green ghost).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import torch
import tyro
from scipy.spatial.transform import Rotation
from torch import nn
from tqdm.auto import tqdm

from crisp_gym.atomic import atomic_path, write_text
from crisp_gym.envs.tracking import terms_from_info
from crisp_gym.html_report import Section, rows_from, write_html_report
from train.models import ACTION_DIM

SEGMENT_FRAMES = 100
BODY_GROUPS = {
    "legs": ("Hip", "Knee", "Ankle", "Toe"),
    "torso": ("Torso", "Spine", "Chest", "Neck", "Head"),
    "arms": ("Thorax", "Shoulder", "Elbow", "Wrist", "Hand"),
}

# A policy maps the observation dict of one or more envs to their actions (numpy in, numpy out).
Policy = Callable[[dict[str, np.ndarray]], np.ndarray]


# --------------------------------------------------------------------------------------------
# Metrics: pure functions over (T, J, 3) joint positions in metres


def _check_motion(name: str, x: np.ndarray, min_frames: int) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim != 3 or x.shape[-1] != 3 or x.shape[0] < min_frames:
        raise ValueError(f"{name} must be (T, J, 3) joint positions with T >= {min_frames}, got shape {x.shape}")
    return x


def rigid_align(source: np.ndarray, target: np.ndarray, fit: slice = slice(None)) -> np.ndarray:
    """``source`` (T, J, 3) moved by the rotation and translation that best map its frames
    ``fit`` onto those of ``target`` (least squares over all their joints; no scale)."""
    source, target = _check_motion("source", source, 1), _check_motion("target", target, 1)
    if source.shape != target.shape:
        raise ValueError(f"source and target must have the same shape, got {source.shape} and {target.shape}")
    a, b = source[fit].reshape(-1, 3), target[fit].reshape(-1, 3)
    if len(a) == 0:
        raise ValueError("the alignment frames are empty")
    a_mean, b_mean = a.mean(axis=0), b.mean(axis=0)
    rotation, _ = Rotation.align_vectors(b - b_mean, a - a_mean)
    return rotation.apply((source - a_mean).reshape(-1, 3)).reshape(source.shape) + b_mean


def segment_mpjpe(pred: np.ndarray, ref: np.ndarray, align: str = "segment",
                  segment: int = SEGMENT_FRAMES) -> float:
    """Mean per-joint position error (mm) over consecutive ``segment``-frame windows.

    Args:
        pred, ref: (T, J, 3) joint positions (m).
        align: ``"segment"`` (WA-MPJPE: each window rigidly aligned on all its frames),
            ``"first_two"`` (W-MPJPE: aligned on its first two frames) or ``"none"``.
        segment: window length; the last window holds the remaining frames.
    """
    pred, ref = _check_motion("pred", pred, 1), _check_motion("ref", ref, 1)
    if pred.shape != ref.shape:
        raise ValueError(f"pred and ref must have the same shape, got {pred.shape} and {ref.shape}")
    fits = {"segment": slice(None), "first_two": slice(0, 2), "none": None}
    if align not in fits:
        raise ValueError(f"align must be one of {sorted(fits)}, got {align!r}")
    if segment < 1:
        raise ValueError(f"segment must be at least 1 frame, got {segment}")
    errors = []
    for start in range(0, len(pred), segment):
        p, r = pred[start:start + segment], ref[start:start + segment]
        if fits[align] is not None:
            p = rigid_align(p, r, fits[align])
        errors.append(np.linalg.norm(p - r, axis=-1))
    return float(np.concatenate(errors).mean() * 1000.0)


def jitter(positions: np.ndarray, fps: float) -> float:
    """Mean norm of the joints' jerk (m/s³): third finite difference × fps³."""
    x = _check_motion("positions", positions, 4)
    jerk = np.diff(x, n=3, axis=0) * fps ** 3
    return float(np.linalg.norm(jerk, axis=-1).mean())


def accel_error(pred: np.ndarray, ref: np.ndarray) -> float:
    """Mean norm of the difference of the joints' accelerations (mm/frame²)."""
    pred, ref = _check_motion("pred", pred, 3), _check_motion("ref", ref, 3)
    if pred.shape != ref.shape:
        raise ValueError(f"pred and ref must have the same shape, got {pred.shape} and {ref.shape}")
    diff = np.diff(pred, n=2, axis=0) - np.diff(ref, n=2, axis=0)
    return float(np.linalg.norm(diff, axis=-1).mean() * 1000.0)


# --------------------------------------------------------------------------------------------
# Rollouts


def torch_policy(actor: nn.Module, scene_aware: bool, device: torch.device | str = "cpu") -> Policy:
    """A :data:`Policy` from an actor returning action means, or (mean, scale) as
    :class:`~train.models.FixedStdGaussian` does; the mean is the action."""
    keys = ["proprio", "targets", "points"] if scene_aware else ["proprio", "targets"]

    @torch.no_grad()
    def act(obs: dict[str, np.ndarray]) -> np.ndarray:
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
    """

    returns: np.ndarray
    lengths: np.ndarray
    success: np.ndarray
    start_frames: np.ndarray
    seconds: float
    clips: np.ndarray

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
    running = np.ones(count, dtype=bool)
    while running.any():
        obs, reward, terminated, truncated, _ = env.step(policy(obs))
        returns += np.where(running, reward, 0.0)
        lengths += running
        success |= running & truncated
        running &= ~(terminated | truncated)
    return EvalResult(returns, lengths, success, info["start_frame"], time.perf_counter() - start, info["clip"])


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
        torques: (T, 69) actuator torques (N·m) at the end of each control step.
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
            torques.append(env.data.actuator_force.copy())
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


# --------------------------------------------------------------------------------------------
# Outputs


def plot_tracking(rollout: Rollout, path: Path, title: str = "") -> None:
    """Largest body error (with the termination threshold) and the reward terms over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    t = (rollout.start_frame + np.arange(len(rollout.max_body_error))) / rollout.control_hz
    ax1.plot(t, rollout.max_body_error, label="largest body error")
    ax1.axhline(rollout.termination_distance, color="r", linestyle="--", label="early termination")
    ax1.set_ylabel("m")
    ax1.set_title(title)
    ax1.legend()
    for key, values in rollout.reward_terms.items():
        ax2.plot(t[1:], values, label=key)
    ax2.set_xlabel("clip time (s)")
    ax2.set_ylabel("weighted reward term")
    ax2.legend(ncol=3, fontsize=8)
    save_figure(fig, path)


def plot_evaluations(progress_csv: Path, path: Path, clip_frames: dict[str, int]) -> None:
    """The periodic evaluations of a run (``progress.csv``): per clip (name → frames), success
    from RSI starts and the share of the clip tracked from frame 0, against training frames."""
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(progress_csv, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get("eval_success_min")]
    if not rows:
        return
    frames = np.array([float(r["frames"]) for r in rows]) / 1e6
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for name, num_frames in clip_frames.items():
        ax1.plot(frames, [float(r[f"eval_success/{name}"]) for r in rows], marker=".", label=name)
        tracked = np.array([float(r[f"eval_frames/{name}"]) for r in rows])
        ax2.plot(frames, tracked / (num_frames - 1), marker=".", label=name)
    ax1.set_ylabel("success from RSI starts")
    ax1.set_ylim(0, 1.02)
    ax1.set_title("deterministic evaluation (mean action)")
    ax1.legend(fontsize=8, ncol=2)
    ax1.grid(alpha=0.3)
    ax2.set_ylabel("share of the clip tracked from frame 0")
    ax2.set_ylim(0, 1.02)
    ax2.set_xlabel("training frames (millions)")
    ax2.grid(alpha=0.3)
    save_figure(fig, path)


def plot_torques(rollout: Rollout, path: Path, title: str = "") -> None:
    """Mean and largest absolute actuator torque per body group over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from crisp_gym.humanoid import DOF_NAMES

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    t = (rollout.start_frame + 1 + np.arange(rollout.steps)) / rollout.control_hz
    magnitude = np.abs(rollout.torques)
    for group, bodies in BODY_GROUPS.items():
        # hinge names are BODY_axis, with an optional L_/R_ side prefix on the body
        columns = [i for i, name in enumerate(DOF_NAMES) if name.rsplit("_", 1)[0].split("_")[-1] in bodies]
        ax1.plot(t, magnitude[:, columns].mean(axis=1), label=group)
        ax2.plot(t, magnitude[:, columns].max(axis=1), label=group)
    ax1.set_ylabel("mean |τ| (N·m)")
    ax1.set_title(title)
    ax1.legend()
    ax2.set_ylabel("max |τ| (N·m)")
    ax2.set_xlabel("clip time (s)")
    save_figure(fig, path)


def save_figure(fig, path: Path) -> None:
    """Lay out, write atomically (100 dpi) and close a matplotlib figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def write_video(images: list[np.ndarray], fps: float, path: Path) -> None:
    """``images`` as an H.264 mp4 (written atomically)."""
    import imageio.v2 as imageio

    with atomic_path(path) as tmp:
        imageio.mimwrite(tmp, images, fps=fps, macro_block_size=8)


def write_json(data: dict[str, Any], path: Path) -> None:
    write_text(path, json.dumps(data, indent=1) + "\n")


# --------------------------------------------------------------------------------------------
# Command line


@dataclass(frozen=True)
class EvalArgs:
    """Evaluate a trained tracking policy on a clip: metrics, plots and a video.

    Attributes:
        policy: run directory, ``checkpoint.pt``, or policy file / directory (``policy.pt``).
        clip: clip name or directory (default: every clip the policy was trained on, each in
            its own subdirectory of ``output``).
        output: directory for report.json, tracking.png, torques.png and rollout.mp4.
        episodes: episodes from RSI start frames (drawn as in training).
        video: render rollout.mp4 of the frame-0 episode (needs headless OpenGL: EGL or OSMesa).
        seed: seed of the RSI start frames.
        device: torch device of the policy.
    """

    policy: Annotated[tyro.conf.Positional[Path], tyro.conf.arg(metavar="RUN_OR_CHECKPOINT")]
    clip: str | None = None
    output: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("runs/eval")
    episodes: int = 100
    video: bool = True
    seed: int = 0
    device: str = "cpu"


def evaluate_policy(policy: Policy, clip: str | os.PathLike, *, episodes: int = 100, seed: int = 0,
                    scene_aware: bool = False, render: bool = False,
                    progress: bool = True, **env_kwargs: Any) -> tuple[dict[str, Any], Rollout]:
    """Success from RSI starts and from frame 0, and the frame-0 rollout's metrics.

    Returns the report entries and the frame-0 rollout (with its images when ``render``);
    ``env_kwargs`` are further ``CrispTrack-v0`` options (as the policy was trained with).
    """
    rsi = evaluate(policy, clip, episodes, scene_aware=scene_aware, seed=seed, **env_kwargs)
    rollout = record_rollout(policy, clip, 0, render=render, scene_aware=scene_aware, progress=progress,
                             **env_kwargs)
    report = {
        "rsi": {"episodes": episodes, "seed": seed, "success_rate": rsi.success_rate,
                "mean_return": rsi.mean_return, "mean_length": float(rsi.lengths.mean()),
                "fps": rsi.fps},
        "from_frame_0": rollout.metrics(),
    }
    return report, rollout


def write_outputs(rollout: Rollout, report: dict[str, Any], output: Path, title: str) -> list[str]:
    """report.json, tracking.png, torques.png, (with images) rollout.mp4 and report.html, the page
    that shows them, in ``output``."""
    output.mkdir(parents=True, exist_ok=True)
    plot_tracking(rollout, output / "tracking.png", title)
    plot_torques(rollout, output / "torques.png", title)
    written = ["report.json", "tracking.png", "torques.png"]
    if rollout.images:
        write_video(rollout.images, rollout.control_hz, output / "rollout.mp4")
        written.append("rollout.mp4")
    write_json(report, output / "report.json")
    write_html_report(output / "report.html", title, [
        Section("Summary", rows=rows_from(report)),
        Section("Tracking and torques", figures=("tracking.png", "torques.png")),
        Section("Rollout from frame 0 (the reference as a ghost)", videos=("rollout.mp4",)),
    ], subtitle="crisp eval")
    written.append("report.html")
    return written


def policy_clips(clips: Any) -> list[str]:
    """The clip names a policy was trained on (its config's ``clip``, tags expanded)."""
    from crisp_gym.registry import resolve_clip_names

    sources = [clips] if isinstance(clips, (str, os.PathLike)) else list(clips)
    return [str(name) for source in sources for name in resolve_clip_names(source)]


def run_eval(args: EvalArgs) -> dict[str, Any]:
    """Evaluate ``args.policy`` and write the outputs; returns the report.

    Without ``--clip`` every clip the policy was trained on is evaluated; with several, each
    gets its own subdirectory of ``--output`` and ``report.json`` there sums them up.
    """
    from train.ppo import load_policy, policy_training_stats

    if args.episodes < 1:
        raise ValueError(f"--episodes must be at least 1, got {args.episodes}")
    actor, cfg = load_policy(args.policy, args.device)
    clips = [args.clip] if args.clip else policy_clips(cfg.clip)
    policy = torch_policy(actor, cfg.scene_aware, args.device)
    reports = {}
    for clip in clips:
        metrics, rollout = evaluate_policy(policy, clip, episodes=args.episodes, seed=args.seed,
                                           scene_aware=cfg.scene_aware, render=args.video,
                                           velocity_feedforward=cfg.velocity_feedforward)
        name = Path(str(clip)).name
        reports[name] = {"policy": str(args.policy), "clip": str(clip), "scene_aware": cfg.scene_aware,
                         "actor": cfg.model.actor, "training": policy_training_stats(args.policy), **metrics}
        write_outputs(rollout, reports[name], args.output / name if len(clips) > 1 else args.output,
                      f"{name}: {Path(args.policy).name}")
    if len(clips) == 1:
        return reports[Path(str(clips[0])).name]
    summary = {"policy": str(args.policy), "clips": reports}
    write_json(summary, args.output / "report.json")
    return summary


def main(argv: list[str] | None = None) -> int:
    """``crisp eval``: see :class:`EvalArgs`."""
    args = tyro.cli(EvalArgs, args=argv, prog="crisp eval")
    report = run_eval(args)
    for name, row in report.get("clips", {Path(report.get("clip", "")).name: report}).items():
        rsi, full = row["rsi"], row["from_frame_0"]
        print(f"{name}: success from RSI starts {rsi['success_rate']:.1%} of {rsi['episodes']}; from frame 0: "
              f"{'yes' if full['success'] else 'no'} ({full['frames_tracked']}/{full['frames_total']} frames); "
              f"W-MPJPE {full['w_mpjpe_mm']:.0f} mm, WA-MPJPE {full['wa_mpjpe_mm']:.0f} mm")
    where = " and one folder per clip, each with its report.html" if "clips" in report else \
        f"; open {args.output}/report.html"
    print(f"wrote {args.output}/report.json{where}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
