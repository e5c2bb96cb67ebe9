"""How long a training run took to bring each clip to a target, from its ``progress.csv``.

For every clip of the run, the first periodic evaluation at which its success from RSI starts
reached ``--success`` *and* the clip was tracked from frame 0 to its end, with the training
frames, the wall time and the compute time (collection + update, without evaluations) up to
that evaluation; then the same for all clips at once (what ``--until-success`` stops on).
Resumed segments are added up. A process stopped with SIGSTOP logs its pause in the iteration it
was in: iterations longer than ``--stall-factor`` times the run's median count as the median in
the compute time, and how much that removed is printed.

    python benchmarks/library_progress.py ~/.cache/crisp-gym/runs/bundled_scratch --success 0.9
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from crisp_gym.policy.files import run_clock


@dataclass(frozen=True)
class Args:
    run: tyro.conf.Positional[Path]
    """run directory (with progress.csv and config.json)"""
    success: float = 0.9
    """success from RSI starts each clip must reach"""
    stall_factor: float = 5.0
    """an iteration longer than this times the median iteration is a stall (the process was
    stopped, or shared the cores with a heavy job) and counts as the median"""


def clip_lengths(names: list[str]) -> dict[str, int]:
    """Frames of each clip at the control rate, as the evaluation counts them."""
    import gymnasium as gym

    import crisp_gym  # noqa: F401  (registers CrispTrack-v0)

    env = gym.make("CrispTrack-v0", clip=names).unwrapped
    lengths = dict(zip(env.task.clip_names, (int(n) for n in env.task.num_frames)))
    env.close()
    return lengths


def main(args: Args) -> dict[str, dict[str, float] | None]:
    with open(args.run / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    names = [key.split("/", 1)[1] for key in rows[0] if key.startswith("eval_success/")]
    if not names:
        raise SystemExit(f"{args.run}/progress.csv has no periodic evaluations (train with --eval-every)")
    lengths = clip_lengths(names)
    wall = run_clock(float(row["time_s"]) for row in rows)
    iteration_s = np.array([float(row["collect_s"]) + float(row["update_s"]) for row in rows])
    median = float(np.median(iteration_s))
    stalls = iteration_s > args.stall_factor * median
    compute = np.cumsum(np.where(stalls, median, iteration_s))

    def reached(row: dict[str, str], name: str) -> bool:
        return (float(row[f"eval_success/{name}"]) >= args.success
                and int(float(row[f"eval_frames/{name}"])) >= lengths[name] - 1)

    results: dict[str, dict[str, float] | None] = {}
    for key, clips in [*((name, [name]) for name in names), ("all clips", names)]:
        hit = next((i for i, row in enumerate(rows)
                    if row.get("eval_success_min") and all(reached(row, c) for c in clips)), None)
        results[key] = None if hit is None else {"frames": float(rows[hit]["frames"]), "wall_min": wall[hit] / 60,
                                                  "compute_min": float(compute[hit]) / 60}
    print(f"{args.run}: first evaluation with success >= {args.success:.0%} from RSI starts and the whole clip "
          f"from frame 0 ({rows[-1]['frames']} frames logged; {int(stalls.sum())} stalled iterations, "
          f"{(iteration_s[stalls] - median).sum() / 60:.1f} min, left out of the compute time)\n")
    print("| clip | frames | wall time (min) | compute time (min) |\n|---|---:|---:|---:|")
    for key, hit in results.items():
        if hit is None:
            print(f"| {key} | not reached | | |")
        else:
            print(f"| {key} | {hit['frames'] / 1e6:.2f} M | {hit['wall_min']:.0f} | {hit['compute_min']:.0f} |")
    return results


if __name__ == "__main__":
    main(tyro.cli(Args))
