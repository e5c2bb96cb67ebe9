"""Package a trained run for shipping: the small policy file, its evaluation and its learning curve.

    crisp ship RUN -o assets/policies/NAME [--clip NAME ...]

writes into ``-o``:

* ``policy.pt``: the actor (state dict, normaliser statistics, config, training totals; see
  :func:`crisp_gym.policy.files.write_policy_file`), what ``crisp demo`` and ``crisp eval`` load;
* ``progress.csv``: the run's training log (6 significant digits), thinned to at most
  ``max_log_rows`` evenly spaced rows plus the evaluations (:func:`thin_progress`; the learning
  curve is drawn from the whole log);
* ``learning_curve.png``: success rate and mean return of the episodes that ended in each
  iteration, against training frames;
* ``evaluation.png``: the run's periodic deterministic evaluations per clip, when it made any;
* ``eval.json``: ``crisp eval``'s report of the shipped file (RSI starts and frame 0), per
  clip under ``"clips"``.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from crisp_gym.atomic import atomic_path


@dataclass(frozen=True)
class ShipArgs:
    """Export a run's policy with its evaluation and learning curve.

    Attributes:
        run: training run directory (checkpoint.pt and progress.csv).
        clip: clip names recorded in the policy and evaluated (default: the run's clips; give
            them when the run names machine-specific directories).
        output: directory to write into (e.g. assets/policies/NAME).
        best: ship the weights of the run's best periodic evaluation (best.pt) instead of
            its last checkpoint.
        with_critic: keep the critic in policy.pt (a milestone that crisp train
            --init-from continues with both networks warm).
        episodes: RSI episodes of the evaluation.
        smooth: iterations in the learning curve's moving average.
        max_log_rows: the shipped progress.csv keeps at most this many evenly spaced
            iterations of a longer log, and every iteration with an evaluation (0: the whole log).
    """

    run: tyro.conf.Positional[Path]
    output: Annotated[Path, tyro.conf.arg(aliases=("-o",))]
    clip: tuple[str, ...] | None = None
    best: bool = False
    with_critic: bool = False
    episodes: int = 100
    smooth: int = 50
    max_log_rows: int = 2000


def read_progress(path: str | Path) -> dict[str, np.ndarray]:
    """A run's ``progress.csv`` as columns (empty cells become NaN)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no training log at {path}")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path} has no rows")
    return {key: np.array([float(r[key]) if r[key] not in ("", None) else np.nan for r in rows])
            for key in rows[0]}


def write_progress(progress: dict[str, np.ndarray], path: Path) -> None:
    """Columns back to CSV with 6 significant digits (the training log's full precision
    doubles the file for nothing a learning curve shows); NaN becomes an empty cell."""
    keys = list(progress)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(keys)
        for row in zip(*(progress[k] for k in keys)):
            writer.writerow(["" if np.isnan(v) else str(int(v)) if v == int(v) else f"{v:.6g}" for v in row])


def thin_progress(progress: dict[str, np.ndarray], max_rows: int) -> dict[str, np.ndarray]:
    """The rows of a training log worth shipping: every ``ceil(rows / max_rows)``-th row, the
    last one, every row with a periodic evaluation (``eval_*``, ``confirm_*`` columns) and the
    rows on either side of a resumed segment's restart of ``time_s``, so that the run's clock
    (:func:`crisp_gym.policy.files.run_clock`) reads the same total. ``max_rows`` 0 keeps all."""
    rows = len(progress["frames"])
    if max_rows <= 0 or rows <= max_rows:
        return progress
    keep = np.zeros(rows, dtype=bool)
    keep[::math.ceil(rows / max_rows)] = True
    keep[-1] = True
    for key, column in progress.items():
        if key.startswith(("eval_", "confirm_")):
            keep |= np.isfinite(column)
    restarts = np.flatnonzero(np.diff(progress["time_s"]) < 0)
    keep[restarts] = keep[restarts + 1] = True
    return {key: column[keep] for key, column in progress.items()}


def _moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over the last ``window`` finite values."""
    out = np.full_like(x, np.nan)
    for i in range(len(x)):
        chunk = x[max(0, i - window + 1):i + 1]
        chunk = chunk[np.isfinite(chunk)]
        if len(chunk):
            out[i] = chunk.mean()
    return out


def plot_learning_curve(progress: dict[str, np.ndarray], path: Path, title: str = "", smooth: int = 10) -> None:
    """Success rate and mean return of the finished episodes against frames (raw and averaged)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from crisp_gym.atomic import save_figure

    frames = progress["frames"] / 1e6
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for ax, key, label in ((ax1, "success_rate", "success rate (RSI episodes)"), (ax2, "mean_return", "mean return")):
        ax.plot(frames, progress[key], color="C0", alpha=0.3, linewidth=0.8)
        ax.plot(frames, _moving_average(progress[key], smooth), color="C0", label=f"{smooth}-iteration mean")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    ax1.set_ylim(0, 1)
    ax1.set_title(title)
    ax1.legend()
    ax2.set_xlabel("training frames (millions)")
    save_figure(fig, path)


def ship(args: ShipArgs) -> dict:
    """Write the files of the module docstring; returns the evaluation report."""
    import shutil

    from crisp_gym.policy.files import BEST_NAME, policy_training_stats, write_policy_file
    from crisp_gym.train.checkpoints import load_policy
    from crisp_gym.train.evaluate import evaluate_policy, policy_clips, write_json
    from crisp_gym.train.rollouts import torch_policy

    progress_path = Path(args.run) / "progress.csv"
    progress = read_progress(progress_path)
    source = Path(args.run) / BEST_NAME if args.best else Path(args.run)
    policy = write_policy_file(source, args.output, clip=args.clip, with_critic=args.with_critic)
    write_progress(thin_progress(progress, args.max_log_rows), args.output / "progress.csv")
    actor, cfg = load_policy(policy)
    clips = policy_clips(cfg.clip)
    plot_learning_curve(progress, args.output / "learning_curve.png", f"{', '.join(clips)}: PPO", args.smooth)
    if (Path(args.run) / "evaluation.png").is_file():
        shutil.copyfile(Path(args.run) / "evaluation.png", args.output / "evaluation.png")
    reports = {}
    for clip in clips:
        reports[Path(clip).name], _ = evaluate_policy(torch_policy(actor, cfg.scene_aware), clip,
                                                      episodes=args.episodes, scene_aware=cfg.scene_aware,
                                                      velocity_feedforward=cfg.velocity_feedforward)
    report = {"policy": policy.name, "actor": cfg.model.actor, "scene_aware": cfg.scene_aware,
              "training": policy_training_stats(policy), "clips": reports}
    write_json(report, args.output / "eval.json")
    return report


def main(argv: list[str] | None = None) -> int:
    """``crisp ship``: see :class:`ShipArgs`."""
    args = tyro.cli(ShipArgs, args=argv, prog="crisp ship")
    report = ship(args)
    print(f"wrote {args.output}/policy.pt, progress.csv, learning_curve.png, eval.json")
    for clip, row in report["clips"].items():
        print(f"{clip}: success from RSI starts {row['rsi']['success_rate']:.1%}, whole clip from frame 0: "
              f"{row['from_frame_0']['success']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
