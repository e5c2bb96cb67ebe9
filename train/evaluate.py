"""Evaluation of a tracking policy: success, world-frame tracking errors, smoothness, plots, video.

``crisp eval RUN_OR_CHECKPOINT [--clip NAME] [-o OUT] [--episodes N] [--video/--no-video]``
rolls the policy's mean action (no exploration noise) out in ``CrispTrack-v0`` twice:

* **RSI starts**: ``--episodes`` episodes in one batched env, from start frames drawn as in
  training (reference state init: 10 % frame 0, else uniform); the success rate and the
  rollout throughput (FPS, env-steps per second including the policy) come from these;
* **from frame 0**: one episode over the whole clip in the single env (deterministic, so one
  is enough). The tracking metrics, the plots and the video come from it;
* with ``--start-every K``, a **start sweep**: one episode from each of frames 0, K, 2K, …
  (batched); ``starts.png`` plots where each ended against where it started, and the report's
  ``start_sweep.failure_clusters`` lists the frames where failed episodes pile up: the parts
  of the clip no start gets through (a fast kick, a rise from a seat), whatever led there, and
  which bodies ended those episodes (``end_bodies``: the body farthest from its reference at
  each episode's end: a hand, a toe, the head).

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

The metrics are :mod:`crisp_gym.train.tracking_metrics`, the roll-outs :mod:`crisp_gym.train.rollouts`
and the plots :mod:`crisp_gym.train.plots`; this module writes the outputs and is the command line.

Outputs in ``-o``: ``report.html`` (the page to open), ``report.json``, ``tracking.png``
(largest body error and reward terms over time), ``torques.png`` (actuator torques by body
group), ``rollout.mp4`` (the simulated humanoid with its reference as a green ghost) and, with
``--start-every``, ``starts.png``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import tyro

from crisp_gym.atomic import atomic_path, write_text
from crisp_gym.html_report import Section, rows_from, write_html_report
from crisp_gym.humanoid import BODY_NAMES
from crisp_gym.train.plots import plot_start_sweep, plot_torques, plot_tracking
from crisp_gym.train.rollouts import (
    EvalResult,
    Policy,
    Rollout,
    evaluate,
    failure_clusters,
    record_rollout,
    torch_policy,
)


def write_video(images: list[np.ndarray], fps: float, path: Path) -> None:
    """``images`` as an H.264 mp4 (written atomically)."""
    import imageio.v2 as imageio

    with atomic_path(path) as tmp:
        imageio.mimwrite(tmp, images, fps=fps, macro_block_size=8)


def write_json(data: dict[str, Any], path: Path) -> None:
    write_text(path, json.dumps(data, indent=1) + "\n")


@dataclass(frozen=True)
class EvalArgs:
    """Evaluate a trained tracking policy on a clip: metrics, plots and a video.

    Attributes:
        policy: run directory, checkpoint.pt, or policy file / directory (policy.pt).
        clip: clip name or directory (default: every clip the policy was trained on, each in
            its own subdirectory of output).
        output: directory for report.json, tracking.png, torques.png and rollout.mp4.
        episodes: episodes from RSI start frames (drawn as in training).
        video: render rollout.mp4 of the frame-0 episode (needs headless OpenGL: EGL or OSMesa).
        seed: seed of the RSI start frames.
        device: torch device of the policy.
        start_every: also roll out one episode from every K-th frame (0, K, 2K, …) and plot
            where each ended (starts.png): where failures pile up is what the policy cannot get
            through (0: no sweep).
    """

    policy: Annotated[tyro.conf.Positional[Path], tyro.conf.arg(metavar="RUN_OR_CHECKPOINT")]
    clip: str | None = None
    output: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("runs/eval")
    episodes: int = 100
    video: bool = True
    seed: int = 0
    device: str = "cpu"
    start_every: int = 0


def evaluate_policy(policy: Policy, clip: str | os.PathLike, *, episodes: int = 100, seed: int = 0,
                    scene_aware: bool = False, render: bool = False,
                    progress: bool = True, **env_kwargs: Any) -> tuple[dict[str, Any], Rollout]:
    """Success from RSI starts and from frame 0, and the frame-0 rollout's metrics.

    Returns the report entries and the frame-0 rollout (with its images when ``render``);
    ``env_kwargs`` are further ``CrispTrack-v0`` options (as the policy was trained with).
    See :func:`start_sweep` for episodes from every K-th frame.
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


def start_sweep(policy: Policy, clip: str | os.PathLike, every: int, num_frames: int, *,
                scene_aware: bool = False, **env_kwargs: Any) -> tuple[dict[str, Any], EvalResult]:
    """One episode from each of frames 0, ``every``, 2·``every``, … of a ``num_frames`` clip.

    Returns the report entry (start and end frames, success, :func:`failure_clusters`) and the
    episodes.
    """
    if every < 1:
        raise ValueError(f"--start-every must be at least 1, got {every}")
    sweep = evaluate(policy, clip, np.arange(0, num_frames - 1, every), scene_aware=scene_aware, **env_kwargs)
    entry = {"every": every, "start_frames": sweep.start_frames.tolist(), "end_frames": sweep.end_frames.tolist(),
             "success": sweep.success.tolist(), "success_rate": sweep.success_rate,
             "end_bodies": [BODY_NAMES[b] for b in sweep.end_bodies],
             "failure_clusters": failure_clusters(sweep.end_frames, ~sweep.success, sweep.end_bodies)}
    return entry, sweep


def write_outputs(rollout: Rollout, report: dict[str, Any], output: Path, title: str,
                  sweep: EvalResult | None = None) -> list[str]:
    """report.json, tracking.png, torques.png, (with images) rollout.mp4, (with a start sweep)
    starts.png and report.html, the page that shows them, in ``output``."""
    output.mkdir(parents=True, exist_ok=True)
    plot_tracking(rollout, output / "tracking.png", title)
    plot_torques(rollout, output / "torques.png", title)
    written = ["report.json", "tracking.png", "torques.png"]
    if sweep is not None:
        plot_start_sweep(sweep, rollout.num_frames - 1, output / "starts.png", f"{title}: where episodes end")
        written.append("starts.png")
    if rollout.images:
        write_video(rollout.images, rollout.control_hz, output / "rollout.mp4")
        written.append("rollout.mp4")
    write_json(report, output / "report.json")
    write_html_report(output / "report.html", title, [
        Section("Summary", rows=rows_from(report)),
        Section("Tracking and torques", figures=("tracking.png", "torques.png")),
        *([Section("Where episodes from every start end", figures=("starts.png",))] if sweep is not None else []),
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
    from crisp_gym.policy.files import policy_training_stats
    from crisp_gym.train.checkpoints import load_policy

    if args.episodes < 1:
        raise ValueError(f"--episodes must be at least 1, got {args.episodes}")
    if args.start_every < 0:
        raise ValueError(f"--start-every must be at least 0 (no sweep), got {args.start_every}")
    actor, cfg = load_policy(args.policy, args.device)
    clips = [args.clip] if args.clip else policy_clips(cfg.clip)
    policy = torch_policy(actor, cfg.scene_aware, args.device)
    reports = {}
    for clip in clips:
        metrics, rollout = evaluate_policy(policy, clip, episodes=args.episodes, seed=args.seed,
                                           scene_aware=cfg.scene_aware, render=args.video,
                                           velocity_feedforward=cfg.velocity_feedforward)
        sweep = None
        if args.start_every:
            metrics["start_sweep"], sweep = start_sweep(policy, clip, args.start_every, rollout.num_frames,
                                                        scene_aware=cfg.scene_aware,
                                                        velocity_feedforward=cfg.velocity_feedforward)
        name = Path(str(clip)).name
        reports[name] = {"policy": str(args.policy), "clip": str(clip), "scene_aware": cfg.scene_aware,
                         "actor": cfg.model.actor, "training": policy_training_stats(args.policy), **metrics}
        write_outputs(rollout, reports[name], args.output / name if len(clips) > 1 else args.output,
                      f"{name}: {Path(args.policy).name}", sweep)
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
        if "start_sweep" in row:
            sweep = row["start_sweep"]
            piles = ", ".join((f"frame {c['first_frame']}" if c["first_frame"] == c["last_frame"] else
                               f"frames {c['first_frame']}-{c['last_frame']}") + f" ({c['episodes']} episodes: "
                              + ", ".join(f"{body} {n}" for body, n in c["bodies"].items()) + ")"
                              for c in sweep["failure_clusters"]) or "nowhere"
            k = sweep["every"]
            suffix = "th" if k % 100 in (11, 12, 13) else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")
            every = "every frame" if k == 1 else f"every {k}{suffix} frame"
            print(f"  from {every}: {sweep['success_rate']:.0%} reach the end; "
                  f"failed episodes pile up at {piles}")
    where = " and one folder per clip, each with its report.html" if "clips" in report else \
        f"; open {args.output}/report.html"
    print(f"wrote {args.output}/report.json{where}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
