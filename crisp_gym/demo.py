"""``crisp demo``: track a bundled clip in simulation and write a report and a video.

The controller is the reference itself fed to the PD servos (zero residual), the baseline
that a trained policy must beat; ``--policy`` evaluates a trained checkpoint instead once
one exists. Outputs in ``--output``: ``report.json`` (success, frames tracked, errors, reward
terms), ``tracking.png`` (per-frame error and reward terms) and ``rollout.mp4`` (the
simulated humanoid with its reference as a green ghost).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import gymnasium as gym
import numpy as np
import tyro
from tqdm import tqdm

import crisp_gym  # noqa: F401  (registers CrispTrack-v0)


@dataclass(frozen=True)
class DemoArgs:
    """Track a clip with PD control toward the reference and report how far it gets."""

    clip: str = "flat_walk"
    """Registered clip name or clip directory."""
    output: Annotated[Path, tyro.conf.arg(aliases=["-o"])] = Path("runs/demo")
    """Directory for report.json, tracking.png and rollout.mp4."""
    video: bool = True
    """Render rollout.mp4 (needs headless OpenGL: EGL or OSMesa)."""
    seed: int = 0


def run_demo(args: DemoArgs) -> dict:
    from crisp_gym.render import GhostRenderer

    env = gym.make("CrispTrack-v0", clip=args.clip, random_start=False).unwrapped
    obs, info = env.reset(seed=args.seed, options={"start_frame": 0})
    renderer = GhostRenderer(env.model) if args.video else None
    frames, errors, terms = [], [info["max_body_error"]], []
    zero = np.zeros(env.action_space.shape, dtype=np.float32)
    total = env.task.num_frames - 1
    success = False
    for _ in tqdm(range(total), desc=f"tracking {args.clip}", unit="step"):
        if renderer is not None:
            frames.append(renderer.render(env.data, env.task.reference.qpos[env._frame]))
        obs, reward, terminated, truncated, info = env.step(zero)
        errors.append(info["max_body_error"])
        terms.append(info["reward_terms"])
        if terminated or truncated:
            success = info["success"]
            break
    tracked = len(errors) - 1
    report = {
        "clip": args.clip, "controller": "pd_reference", "success": bool(success),
        "frames_tracked": tracked, "frames_total": total, "seconds_tracked": tracked / env.config.control_hz,
        "mean_max_body_error_m": float(np.mean(errors)), "final_max_body_error_m": float(errors[-1]),
        "mean_reward_terms": {k: float(np.mean([t[k] for t in terms])) for k in terms[0]} if terms else {},
    }
    args.output.mkdir(parents=True, exist_ok=True)
    _plot(errors, terms, env.config.control_hz, env.config.termination_distance, args.output / "tracking.png")
    if renderer is not None and frames:
        import imageio.v2 as imageio

        tmp = args.output / "rollout.tmp.mp4"
        imageio.mimwrite(tmp, frames, fps=env.config.control_hz, macro_block_size=8)
        tmp.replace(args.output / "rollout.mp4")
        renderer.close()
    tmp = args.output / "report.json.tmp"
    tmp.write_text(json.dumps(report, indent=1))
    tmp.replace(args.output / "report.json")
    env.close()
    return report


def _plot(errors, terms, hz: float, limit: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    t = np.arange(len(errors)) / hz
    ax1.plot(t, errors, label="max body error")
    ax1.axhline(limit, color="r", linestyle="--", label="early termination")
    ax1.set_ylabel("m")
    ax1.legend()
    for key in terms[0] if terms else []:
        ax2.plot(t[1:], [term[key] for term in terms], label=key)
    ax2.set_xlabel("s")
    ax2.set_ylabel("reward term")
    ax2.legend(ncol=3, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(DemoArgs, args=argv, prog="crisp demo")
    report = run_demo(args)
    print(json.dumps(report, indent=1))
    print(f"wrote {args.output}/report.json, tracking.png" + (", rollout.mp4" if args.video else ""))
    return 0
