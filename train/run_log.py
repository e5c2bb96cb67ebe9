"""A run's log: ``progress.csv`` rows, and the same scalars to TorchRL's experiment loggers."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from crisp_gym.atomic import atomic_path

CSV_FIELDS = ("iteration", "frames", "time_s", "fps", "episodes", "mean_return", "mean_length", "success_rate",
              "loss_objective", "loss_critic", "kl_approx", "clip_fraction", "explained_variance",
              "collect_s", "env_s", "update_s")


def _tracker(kind: str, directory: Path):
    """A ``torchrl.record.loggers`` logger of ``kind`` writing under ``directory / "trackers"``."""
    from torchrl.record.loggers import get_logger  # noqa: PLC0415 - only runs that ask for trackers

    try:
        return get_logger(kind, logger_name=str(directory / "trackers"), experiment_name=directory.name)
    except ImportError as err:
        raise ModuleNotFoundError(f"--loggers {kind} needs the {err.name or kind} package: pip install "
                                  "'crisp-gym[tracking]' (TensorBoard, W&B) or the package itself") from None


def _kind(column: str) -> str:
    """What a column measures, without its clip (``start_failures/stairs_up`` → ``start_failures``)."""
    return column.split("/", 1)[0]


class RunLogger:
    """``progress.csv`` rows, and the same scalars to TorchRL's experiment loggers (``kinds``)."""

    def __init__(self, directory: Path, append: bool, iteration: int = 0, extra_fields: tuple[str, ...] = (),
                 kinds: tuple[str, ...] = ()):
        self.path = directory / "progress.csv"
        self.fields = CSV_FIELDS + tuple(extra_fields)
        new = not (append and self.path.exists())
        if not new:
            self._truncate(iteration)
        self._file = open(self.path, "w" if new else "a", newline="")
        self._csv = csv.DictWriter(self._file, fieldnames=self.fields, extrasaction="ignore")
        if new:
            self._csv.writeheader()
        self._trackers = [_tracker(kind, directory) for kind in kinds]

    def _truncate(self, iteration: int) -> None:
        """Drop rows after ``iteration``: a run that died between checkpoints logged
        iterations that resuming repeats. A log written by a version with fewer columns gains
        the new ones (empty in its rows)."""
        with open(self.path, newline="") as f:
            reader = csv.DictReader(f)
            rows, header = list(reader), tuple(reader.fieldnames or ())
        new_kinds = {_kind(name) for name in set(self.fields) - set(header)}
        if not set(header) <= set(self.fields) or new_kinds & {_kind(name) for name in header}:
            # a missing column of a kind the log already has is another clip, not a newer version
            raise ValueError(f"{self.path} has the columns {list(header)}, but this run logs {list(self.fields)}: "
                             f"resume with the clips the run started with")
        if header == self.fields and all(int(row["iteration"]) <= iteration for row in rows):
            return
        with atomic_path(self.path) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(row for row in rows if int(row["iteration"]) <= iteration)

    def log(self, row: dict[str, float]) -> None:
        self._csv.writerow(row)
        self._file.flush()
        for tracker in self._trackers:
            for key, value in row.items():
                if key not in ("iteration", "frames") and isinstance(value, (int, float)) and math.isfinite(value):
                    tracker.log_scalar(key, float(value), step=int(row["frames"]))

    def close(self) -> None:
        self._file.close()
        for tracker in self._trackers:
            writer = getattr(tracker, "experiment", None)
            if hasattr(writer, "close"):  # TensorBoard's SummaryWriter holds its event file open
                writer.close()


def clip_fields(clip_names: list[str], evaluated: bool) -> tuple[str, ...]:
    """The per-clip columns of ``progress.csv``: the adaptive sampler's failure mass, the
    probability of drawing the clip and, with periodic evaluation (``evaluated``), the
    evaluation's success and frames from frame 0 and the success of the stop rule's
    confirmation (empty in the rows without one; there whether or not the run confirms, so that
    a run resumed with other stop options keeps its columns)."""
    fields = [f"start_failures/{name}" for name in clip_names]
    fields += [f"clip_probability/{name}" for name in clip_names]
    if evaluated:
        fields += [f"eval_{kind}/{name}" for name in clip_names for kind in ("success", "frames")]
        fields += ["eval_success_min"]
        fields += [f"confirm_success/{name}" for name in clip_names]
    return tuple(fields)


def evaluation_row(results: dict[str, dict[str, float]]) -> dict[str, float]:
    row = {}
    for name, r in results.items():
        row[f"eval_success/{name}"] = r["success"]
        row[f"eval_frames/{name}"] = r["frames"]
    row["eval_success_min"] = min(r["success"] for r in results.values())
    return row


def confirmation_row(results: dict[str, dict[str, float]]) -> dict[str, float]:
    return {f"confirm_success/{name}": r["success"] for name, r in results.items()}
