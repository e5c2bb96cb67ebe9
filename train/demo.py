"""``crisp demo``: evaluate the trained policy shipped for a bundled clip; write a report, plots and a video.

The policy comes from ``assets/policies/<clip>/policy.pt`` (or ``--policy``); it is evaluated
as ``crisp eval`` does (success from reference-state-init starts and over the whole clip from
frame 0, W-/WA-MPJPE, jitter, acceleration error). The PD-reference controller (the reference
pose fed to the PD servos, zero residual), the baseline that the policy must beat, is evaluated
the same way and reported as a comparison row. Clips without a shipped policy get the
PD-reference controller alone.

Outputs in ``--output``: ``report.html`` (the page to open), ``report.json``, ``tracking.png``
(largest body error and reward terms over time), ``torques.png`` and ``rollout.mp4`` (the
simulated humanoid with its reference as a green ghost).

``--all`` runs the demo for every bundled clip, each into its own subdirectory, and writes
``all_clips.mp4`` (the clips' videos one after another, each captioned) and a ``report.json``
that sums them up.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import tyro

from crisp_gym.bundled import SHIPPED_POLICIES, display_path


@dataclass(frozen=True)
class DemoArgs:
    """Track a clip with its shipped policy (and the PD-reference baseline) and report how well.

    Attributes:
        clip: registered clip name or clip directory.
        all: every bundled clip, one after another (clip is then ignored).
        policy: policy file, directory or training run (default: the one shipped for clip).
        output: directory for report.json, tracking.png, torques.png and rollout.mp4.
        episodes: episodes from reference-state-init start frames per controller.
        video: render rollout.mp4 (needs headless OpenGL: EGL or OSMesa).
        seed: seed of the start frames.
    """

    clip: str = "flat_walk"
    all: bool = False
    policy: Path | None = None
    output: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("runs/demo")
    episodes: int = 64
    video: bool = True
    seed: int = 0


def shipped_policy(clip: str) -> Path | None:
    """The policy shipped in ``assets/policies`` for a clip name, if any: its own
    (``assets/policies/<clip>``), else one trained on several clips including it (its
    ``eval.json`` lists the clips it was shipped for)."""
    name = Path(clip).name
    own = SHIPPED_POLICIES / name / "policy.pt"
    if own.is_file():
        return own
    for report in sorted(SHIPPED_POLICIES.glob("*/eval.json")):
        if name in json.loads(report.read_text()).get("clips", {}) and (report.parent / "policy.pt").is_file():
            return report.parent / "policy.pt"
    return None


def run_demo(args: DemoArgs) -> dict[str, Any]:
    """Evaluate, write the outputs and return the report."""
    from crisp_gym.policy.files import load_actor, policy_training_stats
    from crisp_gym.train.evaluate import evaluate_policy, write_outputs
    from crisp_gym.train.rollouts import torch_policy, zero_policy

    if args.episodes < 1:
        raise ValueError(f"--episodes must be at least 1, got {args.episodes}")
    policy_path = args.policy or shipped_policy(args.clip)
    baseline, baseline_rollout = evaluate_policy(zero_policy, args.clip, episodes=args.episodes, seed=args.seed,
                                                 render=args.video and policy_path is None)
    baseline = {"controller": "pd_reference", **baseline}
    if policy_path is None:
        print(f"no policy shipped for {args.clip!r}: evaluating the PD-reference controller alone")
        report, rollout = {"clip": args.clip, **baseline}, baseline_rollout
    else:
        policy = load_actor(policy_path)
        metrics, rollout = evaluate_policy(torch_policy(policy.actor, policy.scene_aware), args.clip,
                                           episodes=args.episodes, seed=args.seed, scene_aware=policy.scene_aware,
                                           render=args.video, velocity_feedforward=policy.velocity_feedforward)
        report = {"clip": args.clip, "controller": "policy", "policy": display_path(policy_path),
                  "actor": policy.model.actor, "training": policy_training_stats(policy_path), **metrics,
                  "comparison": {"pd_reference": baseline}}
    write_outputs(rollout, report, args.output, f"{args.clip}: {report['controller']}")
    return report


def run_all(args: DemoArgs) -> dict[str, Any]:
    """:func:`run_demo` for every bundled clip, ``all_clips.mp4`` and a summary report."""
    from dataclasses import replace

    from crisp_gym.atomic import write_text
    from crisp_gym.registry import clips_with_tag

    reports = {}
    for name in clips_with_tag("bundled"):
        reports[name] = run_demo(replace(args, clip=name, output=args.output / name, all=False))
    if args.video:
        join_videos({name: args.output / name / "rollout.mp4" for name in reports}, args.output / "all_clips.mp4")
    summary = {"clips": reports}
    write_text(args.output / "report.json", json.dumps(summary, indent=1) + "\n")
    return summary


def join_videos(videos: dict[str, Path], path: Path) -> None:
    """The videos one after another, each frame captioned with its name (written atomically)."""
    import cv2
    import imageio.v2 as imageio

    from crisp_gym.atomic import atomic_path

    fps = imageio.get_reader(next(iter(videos.values()))).get_meta_data()["fps"]
    with atomic_path(path) as tmp:
        with imageio.get_writer(tmp, fps=fps, macro_block_size=8) as writer:
            for caption, video in videos.items():
                for frame in imageio.get_reader(video):
                    frame = frame.copy()
                    cv2.putText(frame, caption, (16, 40), cv2.FONT_HERSHEY_SIMPLEX, 1.1, (255, 255, 255), 2,
                                cv2.LINE_AA)
                    writer.append_data(frame)


def main(argv: list[str] | None = None) -> int:
    """``crisp demo``: see :class:`DemoArgs`."""
    args = tyro.cli(DemoArgs, args=argv, prog="crisp demo")
    if args.all:
        summary = run_all(args)
        for name, report in summary["clips"].items():
            _print_rows(report, f"{name}: ")
        print(f"wrote {args.output}/report.json" + (", all_clips.mp4" if args.video else "")
              + " and one folder per clip")
        return 0
    report = run_demo(args)
    _print_rows(report)
    names = ["report.json", "tracking.png", "torques.png"] + (["rollout.mp4"] if args.video else [])
    print(f"wrote {', '.join(str(args.output / n) for n in names)}; open {args.output / 'report.html'}")
    return 0


def _print_rows(report: dict[str, Any], prefix: str = "") -> None:
    for row in [report] + list(report.get("comparison", {}).values()):
        full = row["from_frame_0"]
        print(f"{prefix}{row['controller']:>12}: success from RSI starts {row['rsi']['success_rate']:.0%}; whole "
              f"clip from frame 0: {'yes' if full['success'] else 'no'} ({full['frames_tracked']}/"
              f"{full['frames_total']} frames), W-MPJPE {full['w_mpjpe_mm']:.0f} mm, WA-MPJPE "
              f"{full['wa_mpjpe_mm']:.0f} mm")
