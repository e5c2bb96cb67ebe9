"""Tracking-policy success on an occluded-support clip, with vs without contact completion
(the paper's Fig. 4 claim), on the CPU training profile.

    python benchmarks/contact_policy.py --frames 2000000 --out results/contact_policy
    python benchmarks/contact_policy.py --kind platform_step --frames 2000000 --out results/contact_policy_platform

1. ``crisp synth``: a person sits down on a chair seen by the ``low`` camera, which never sees
   the seat's top (the sitter and the camera's height hide it); or (``--kind platform_step``)
   steps onto a platform that the ``upper_body`` camera keeps out of view.
2. ``crisp reconstruct`` twice from that input: ``--contacts kinematic`` (the seat comes back as a
   contact primitive) and ``--contacts none`` (no seat).
3. One policy per scene, trained with the same profile, seed and frame budget
   (``crisp_gym.train.config.cpu_profile``), each evaluated in its own scene; the PD-reference controller
   (zero residual) in both scenes is the untrained baseline.

Besides success and MPJPE, the table gives the mean absolute torque of the hip, knee and ankle
actuators over the frames where the reference sits (pelvis more than 0.2 m below its height at
frame 0) that the frame-0 rollout tracked: a seat carries the body's weight, a squat over a
missing seat must hold it in the legs.

Runs are resumable: an interrupted run continues from its checkpoint when the command is
repeated with the same ``--out``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import tyro

from crisp_gym.humanoid import DOF_NAMES
from crisp_gym.policy.files import CHECKPOINT_NAME, load_checkpoint
from crisp_gym.reconstruct.pipeline import ReconstructArgs
from crisp_gym.reconstruct.pipeline import run as run_reconstruct
from crisp_gym.synth.truth import write_synth_input
from crisp_gym.synth.video import SynthSpec, SynthVideoConfig, render_synth_video
from crisp_gym.train.checkpoints import load_policy
from crisp_gym.train.config import cpu_profile
from crisp_gym.train.evaluate import evaluate_policy
from crisp_gym.train.ppo import train
from crisp_gym.train.rollouts import Rollout, torch_policy, zero_policy

SCENES = {"with completion": "kinematic", "without completion": "none"}
VIEWS = {"chair_sit": "low", "platform_step": "upper_body"}
LEG_ACTUATORS = np.array([name.split("_")[1] in ("Hip", "Knee", "Ankle") for name in DOF_NAMES])
SEATED_DROP = 0.2  # m below the standing pelvis height: the reference sits


@dataclass(frozen=True)
class Args:
    """Benchmark options.

    Attributes:
        out: directory for the input, the clips, the runs and ``results.json``.
        kind: the occluded-support case: ``chair_sit`` (seen by the ``low`` camera, which never
            sees the seat's top) or ``platform_step`` (seen by the ``upper_body`` camera, which
            never sees the platform).
        seed: seed of the synthetic video and of training.
        frames: training frames per policy.
        episodes: RSI evaluation episodes per policy.
    """

    out: Path = Path("results/contact_policy")
    kind: Literal["chair_sit", "platform_step"] = "chair_sit"
    seed: int = 0
    frames: int = 2_000_000
    episodes: int = 100


def _clip(args: Args, contacts: str) -> Path:
    source = args.out / "input"
    if not (source / "input.npz").is_file():
        spec = SynthSpec(args.kind, args.seed, VIEWS[args.kind])
        video = render_synth_video(spec, SynthVideoConfig(), progress=False)
        write_synth_input(source, video, overwrite=True)
    clip = args.out / f"clip_{contacts}"
    if not (clip / "scene.xml").is_file():
        run_reconstruct(ReconstructArgs(input=source / "input.npz", motion=source / "motion_camera.npz",
                                        name=f"{args.kind}_{contacts}", output=clip, contacts=contacts, overwrite=True))
    return clip


def _train(args: Args, clip: Path, name: str) -> tuple[Path, int]:
    """The run directory and its training frames (a finished run is kept, an interrupted one resumed)."""
    run = args.out / f"run_{name}"
    cfg = cpu_profile(clip=str(clip), output=run, frames=args.frames, seed=args.seed)
    done = 0
    if (run / CHECKPOINT_NAME).is_file():
        done = load_checkpoint(run)["frames"]
        cfg = replace(cfg, resume=True)
    if done < args.frames:
        done = train(cfg).frames
    return run, done


def seated_leg_torque(rollout: Rollout) -> float:
    """Mean |torque| (N·m) of the leg actuators over the tracked steps where the reference sits."""
    pelvis = rollout.ref_body_pos[1:, 0, 2]
    seated = pelvis < rollout.ref_body_pos[0, 0, 2] - SEATED_DROP
    if not seated.any():
        return float("nan")
    return float(np.abs(rollout.torques[seated][:, LEG_ACTUATORS]).mean())


def _summary(report: dict, rollout: Rollout) -> dict:
    frame0 = report["from_frame_0"]
    return {"seated_leg_torque_nm": seated_leg_torque(rollout),"rsi_success": report["rsi"]["success_rate"], "rsi_mean_length": report["rsi"]["mean_length"],
            "frame0_success": frame0["success"], "frame0_tracked": frame0["frames_tracked"],
            "frame0_total": frame0["frames_total"], "w_mpjpe_mm": frame0["w_mpjpe_mm"],
            "mpjpe_mm": frame0["mpjpe_mm"]}


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(Args, args=argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    for label, contacts in SCENES.items():
        clip = _clip(args, contacts)
        primitives = json.loads((clip / "primitives.json").read_text())
        baseline = evaluate_policy(zero_policy, clip, episodes=args.episodes, seed=args.seed, progress=False)
        run, frames = _train(args, clip, contacts)
        actor, cfg = load_policy(run)
        report = evaluate_policy(torch_policy(actor, cfg.scene_aware), clip, episodes=args.episodes,
                                 seed=args.seed, progress=False)
        results[label] = {"clip": str(clip), "primitives": len(primitives),
                          "contact_primitives": sum(b.get("source") == "contact" for b in primitives),
                          "training_frames": frames,
                          "pd_reference": _summary(*baseline), "policy": _summary(*report)}
    (args.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    print("| scene | primitives (contact) | controller | success from RSI starts | whole clip from frame 0 "
          "| W-MPJPE (mm) | MPJPE (mm) | leg torque while seated (N·m) |")
    print("|---|---|---|---|---|---|---|---|")
    for label, row in results.items():
        for controller in ("pd_reference", "policy"):
            s = row[controller]
            torque = f"{s['seated_leg_torque_nm']:.0f}" if np.isfinite(s["seated_leg_torque_nm"]) else "—"
            name = "PD reference" if controller == "pd_reference" else f"policy, {row['training_frames'] / 1e6:.1f} M frames"
            print(f"| {label} | {row['primitives']} ({row['contact_primitives']}) | {name} | {s['rsi_success']:.0%} | "
                  f"{'yes' if s['frame0_success'] else 'no'}: {s['frame0_tracked']} / {s['frame0_total']} | "
                  f"{s['w_mpjpe_mm']:.0f} | {s['mpjpe_mm']:.0f} | {torque} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
