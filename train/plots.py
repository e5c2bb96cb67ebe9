"""The evaluation's figures: tracking error and reward terms over a roll-out, torques by body group,
and the periodic evaluations of a training run."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from crisp_gym.atomic import save_figure
from crisp_gym.train.rollouts import EvalResult, Rollout, failure_clusters

BODY_GROUPS = {
    "legs": ("Hip", "Knee", "Ankle", "Toe"),
    "torso": ("Torso", "Spine", "Chest", "Neck", "Head"),
    "arms": ("Thorax", "Shoulder", "Elbow", "Wrist", "Hand"),
}


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
    from RSI starts (rings: the stop rule's confirmations on other starts) and the share of the
    clip tracked from frame 0, against training frames."""
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
    any_confirmed = False
    for name, num_frames in clip_frames.items():
        line, = ax1.plot(frames, [float(r[f"eval_success/{name}"]) for r in rows], marker=".", label=name)
        confirmed = [(x, float(r[f"confirm_success/{name}"])) for x, r in zip(frames, rows)
                     if r.get(f"confirm_success/{name}")]
        if confirmed:  # the stop rule's confirmations on other starts, as rings
            ax1.scatter(*zip(*confirmed), s=40, facecolors="none", edgecolors=line.get_color())
            any_confirmed = True
        tracked = np.array([float(r[f"eval_frames/{name}"]) for r in rows])
        ax2.plot(frames, tracked / (num_frames - 1), marker=".", label=name)
    if any_confirmed:  # one legend entry for every clip's rings
        ax1.scatter([], [], s=40, facecolors="none", edgecolors="grey", label="confirmation (other starts)")
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


def plot_start_sweep(sweep: EvalResult, last_frame: int, path: Path, title: str = "") -> None:
    """Where each episode of a start sweep ended (y) against where it started (x): successes
    reach ``last_frame``; failures that line up horizontally are places no start gets past, each
    labelled with the body that ended most of its episodes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    ax.plot([0, last_frame], [0, last_frame], color="0.7", linewidth=1, label="start = end")
    ok = sweep.success
    ax.scatter(sweep.start_frames[ok], sweep.end_frames[ok], color="tab:green", s=18, label="reached the end")
    ax.scatter(sweep.start_frames[~ok], sweep.end_frames[~ok], color="tab:red", s=18, label="terminated")
    labelled: list[int] = []  # right of the diagonal nothing is plotted; the biggest piles first
    for cluster in failure_clusters(sweep.end_frames, ~ok, sweep.end_bodies):
        if all(abs(cluster["first_frame"] - y) > 0.04 * last_frame for y in labelled):
            body, count = next(iter(cluster["bodies"].items()))
            ax.text(last_frame, cluster["first_frame"], f"{body}: {count} of {cluster['episodes']} ended here ",
                    fontsize=8, color="tab:red", ha="right", va="center")
            labelled.append(cluster["first_frame"])
    ax.set_xlabel("start frame")
    ax.set_ylabel("frame the episode ended at")
    ax.set_xlim(-1, last_frame + 1)
    ax.set_ylim(-1, last_frame + 3)
    ax.set_title(title)
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(alpha=0.3)
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
