"""Policy files: a training checkpoint (``checkpoint.pt``, ``best.pt``) and the small policy file
shipped to users (``policy.pt``); reading both, writing the second.

A checkpoint (written by :func:`crisp_gym.train.checkpoints.save_checkpoint`) holds
``format_version``, ``iteration``, ``frames``, ``config`` (the training config as plain values),
``actor``, ``critic``, ``optimizer`` and random-generator state. A policy file holds
``format_version``, ``kind: "policy"``, ``config``, ``actor`` (observation-normaliser statistics
included), ``training`` (iterations, frames, wall time) and, optionally, ``critic``.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from crisp_gym.atomic import atomic_path
from crisp_gym.envs.config import TrackConfig
from crisp_gym.file_errors import reading
from crisp_gym.policy.model_config import ModelConfig, model_config
from crisp_gym.policy.networks import FixedStdGaussian, ObsNormalizer, build_actor
from crisp_gym.torch_file import load_tensors

CHECKPOINT_NAME = "checkpoint.pt"
BEST_NAME = "best.pt"  # the checkpoint of the best periodic evaluation so far
CHECKPOINT_FORMAT = 1
POLICY_NAME = "policy.pt"
POLICY_FORMAT = 1


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """A checkpoint's contents (tensors and plain Python values only)."""
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    state = load_tensors(path)
    if not isinstance(state, dict) or state.get("format_version") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a version-{CHECKPOINT_FORMAT} crisp-gym training checkpoint")
    return state


def read_policy_source(path: str | Path) -> tuple[Path, dict[str, Any]]:
    """(file, contents) of a run directory (its ``policy.pt`` if it has one, else its
    ``checkpoint.pt``), a checkpoint or a policy file."""
    path = Path(path)
    if path.is_dir():
        path = path / POLICY_NAME if (path / POLICY_NAME).is_file() else path / CHECKPOINT_NAME
    if not path.is_file():
        raise FileNotFoundError(f"no policy at {path}: expected a run directory, a {CHECKPOINT_NAME} "
                                f"or a {POLICY_NAME}")
    state = load_tensors(path)
    if not isinstance(state, dict) or not (
            state.get("kind") == "policy" and state.get("format_version") == POLICY_FORMAT
            or state.get("format_version") == CHECKPOINT_FORMAT and "critic" in state):
        raise ValueError(f"{path} is neither a crisp-gym training checkpoint nor a policy file "
                         f"(version {CHECKPOINT_FORMAT}/{POLICY_FORMAT})")
    return path, state


@dataclass(frozen=True)
class LoadedPolicy:
    """A trained actor and the training config it was saved with.

    Attributes:
        actor: (loc, scale) from the observation tensors, normaliser included, in eval mode.
        config: the training config as saved (plain values; :func:`crisp_gym.train.config.config_from_dict`
            makes a ``TrainConfig`` of it).
        path: the file it was read from.
    """

    actor: FixedStdGaussian
    config: dict[str, Any]
    path: Path

    @property
    def model(self) -> ModelConfig:
        return model_config(self.config)

    @property
    def scene_aware(self) -> bool:
        return bool(self.config["scene_aware"])

    @property
    def normalize_obs(self) -> bool:
        return bool(self.config["normalize_obs"])

    @property
    def velocity_feedforward(self) -> bool:
        """The env option the policy was trained with (files from before it existed: off)."""
        return bool(self.config.get("velocity_feedforward", False))


def _num_points(actor_state: dict[str, torch.Tensor], config: dict[str, Any]) -> int:
    """The points a saved actor takes: 0 scene-blind; a flat encoder's from its weights; a PointNet
    takes any number (the env's default is as good as any)."""
    if not config["scene_aware"]:
        return 0
    flat = actor_state.get("actor.point_encoder.linear.weight")
    return flat.shape[1] // 3 if flat is not None else TrackConfig().num_points


def load_actor(path: str | Path, device: torch.device | str = "cpu") -> LoadedPolicy:
    """The trained actor of a run directory, checkpoint or policy file (see :func:`read_policy_source`)."""
    path, state = read_policy_source(path)
    try:
        with reading(path, "policy"):
            config = dict(state["config"])
            model = model_config(config)
            num_targets = state["actor"]["actor.normalizer.targets.mean"].shape[0]
            normalizer = ObsNormalizer(num_targets, clip=model.obs_clip, enabled=config["normalize_obs"])
            actor = FixedStdGaussian(build_actor(model, num_targets, _num_points(state["actor"], config), normalizer),
                                     model.action_std)
            actor.load_state_dict(state["actor"])
    except RuntimeError as err:  # torch: weights whose shapes disagree with the configured model
        raise ValueError(f"{path}: a damaged or inconsistent policy ({err})") from err
    return LoadedPolicy(actor.to(device).eval(), config, path)


def write_policy_file(run: str | Path, output: str | Path, clip: str | tuple[str, ...] | None = None,
                      with_critic: bool = False) -> Path:
    """Write a run's actor as a small self-contained policy file, ``output/policy.pt``.

    It holds the actor's ``state_dict`` (observation-normaliser statistics included), the
    run's config and its training totals (iterations, frames, wall time from
    ``progress.csv``): all :func:`load_actor` needs, without the critic and optimiser state
    that make a checkpoint several times larger.

    Args:
        run: run directory or checkpoint file.
        output: directory for ``policy.pt`` (created).
        clip: clip name(s) to record in the config instead of the run's (e.g. registered names
            in place of machine-specific directories).
        with_critic: keep the critic too (a training milestone: ``crisp train --init-from``
            then continues with both networks warm; the optimiser state is never kept).
    """
    checkpoint = Path(run) / CHECKPOINT_NAME if Path(run).is_dir() else Path(run)
    state = load_checkpoint(checkpoint)
    config = dict(state["config"])
    if clip is not None:
        config["clip"] = [clip] if isinstance(clip, str) else list(clip)
    payload = {
        "format_version": POLICY_FORMAT,
        "kind": "policy",
        "config": config,
        "actor": state["actor"],
        "training": policy_training_stats(checkpoint),
    }
    if with_critic:
        payload["critic"] = state["critic"]
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    path = output / POLICY_NAME
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def policy_training_stats(path: str | Path) -> dict[str, float | None]:
    """Training totals of a run directory, checkpoint or policy file: iterations, frames and
    wall time (``None`` when the run's ``progress.csv`` is not next to its checkpoint)."""
    path, state = read_policy_source(path)
    if state.get("kind") == "policy":
        return dict(state["training"])
    return {"iterations": state["iteration"], "frames": state["frames"],
            "wall_time_s": run_wall_time(path.parent / "progress.csv")}


def run_wall_time(progress_csv: str | Path) -> float | None:
    """Seconds a run trained in total, from its ``progress.csv`` (resumed segments added up);
    ``None`` without the file."""
    path = Path(progress_csv)
    if not path.is_file():
        return None
    with open(path, newline="") as f:
        clock = run_clock(float(row["time_s"]) for row in csv.DictReader(f))
    return clock[-1] if clock else 0.0


def run_clock(times_s: Iterable[float]) -> list[float]:
    """Seconds since a run began at each ``progress.csv`` row, from the rows' ``time_s``:
    each resumed segment restarts its own clock, so the segments before it are added."""
    clock, offset, last = [], 0.0, 0.0
    for elapsed in times_s:
        if elapsed < last:  # a resumed segment restarts its clock
            offset += last
        last = elapsed
        clock.append(offset + elapsed)
    return clock
