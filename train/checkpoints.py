"""Saving a run's state and reading a trained policy back as a :class:`~crisp_gym.train.config.TrainConfig` run.

The file formats themselves (names, versions, the policy file) are :mod:`crisp_gym.policy.files`,
below the trainer, where the demo and ``crisp export`` read them too.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from crisp_gym.atomic import atomic_path
from crisp_gym.file_errors import reading
from crisp_gym.policy.files import CHECKPOINT_FORMAT, load_actor
from crisp_gym.policy.networks import FixedStdGaussian
from crisp_gym.train.config import TrainConfig, config_from_dict, config_to_dict

if TYPE_CHECKING:
    from crisp_gym.train.ppo import Agent

ARCHITECTURE_FIELDS = ("scene_aware", "model", "normalize_obs")
"""Config fields a run's weights are tied to: resuming or warm-starting must keep them."""

_TRANSFORMER_ONLY = ("latent_dim", "ff_dim", "num_layers", "num_heads", "num_point_tokens")
_SCENE_AWARE_ONLY = ("point_encoder", "pointnet_hidden", "num_point_tokens")
# Model options that shape no weight: the exploration noise (set anew on every start) and the
# spread of the initial action head (loaded weights replace it).
_NOT_IN_WEIGHTS = ("action_std", "init_action_std")


def architecture(cfg: TrainConfig) -> dict[str, Any]:
    """The :data:`ARCHITECTURE_FIELDS` of ``cfg`` (the model's options as ``model.<name>``) without
    the model options that build nothing in its networks: a scene-blind actor has no point
    encoder, an MLP actor no transformer, a transformer no MLP, and no network depends on the
    exploration noise ``action_std`` (a warm start or a resumed run may change it)."""
    unused = set(_NOT_IN_WEIGHTS) | (set(_TRANSFORMER_ONLY) if cfg.model.actor == "mlp" else {"mlp_actor_hidden"})
    if not cfg.scene_aware:
        unused |= set(_SCENE_AWARE_ONLY)
    out = {f"model.{k}": v for k, v in asdict(cfg.model).items() if k not in unused}
    out.update({name: getattr(cfg, name) for name in ARCHITECTURE_FIELDS if name != "model"})
    return out


def save_checkpoint(path: str | Path, agent: Agent, optimizer: torch.optim.Optimizer, iteration: int,
                    frames: int, cfg: TrainConfig, generator: torch.Generator,
                    start_failures: list[np.ndarray] | None = None, evaluation_score: float | None = None) -> Path:
    """Write a checkpoint atomically (a temporary file, synced, then renamed over ``path``).

    ``start_failures``: the adaptive start sampler's failure counts per clip, so a resumed run
    starts where the interrupted one was failing. ``evaluation_score``: the
    :func:`evaluation_score` of the weights, for the best-evaluated checkpoint.
    """
    path = Path(path)
    state = {
        "format_version": CHECKPOINT_FORMAT,
        "iteration": iteration,
        "frames": frames,
        "config": config_to_dict(cfg),
        "actor": agent.actor.state_dict(),
        "critic": agent.critic.state_dict(),
        "optimizer": optimizer.state_dict(),
        "generator": generator.get_state(),
        "torch_rng": torch.get_rng_state(),
    }
    if evaluation_score is not None:
        state["evaluation_score"] = float(evaluation_score)
    if start_failures is not None:
        state["start_failures"] = [torch.from_numpy(np.asarray(f, dtype=np.float64)) for f in start_failures]
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(state, f)
        f.flush()
        os.fsync(f.fileno())
    return path


def load_policy(path: str | Path, device: torch.device | str = "cpu") -> tuple[FixedStdGaussian, TrainConfig]:
    """The trained actor ((loc, scale) from observations, normaliser included) and its config.

    ``path`` is a run directory (its ``policy.pt`` if it has one, else its ``checkpoint.pt``),
    a training checkpoint or a policy file (:func:`crisp_gym.policy.files.write_policy_file`).
    """
    loaded = load_actor(path, device)
    with reading(loaded.path, "policy"):
        return loaded.actor, config_from_dict(loaded.config)


def check_resumable(saved: TrainConfig, cfg: TrainConfig, action: str = "resume") -> None:
    """Refuse to continue ``saved``'s weights under a config with another :func:`architecture`."""
    before, now = architecture(saved), architecture(cfg)
    changed = [name for name in before.keys() | now.keys() if before.get(name) != now.get(name)]
    if changed:
        changed.sort()
        raise ValueError(f"cannot {action}: {', '.join(changed)} differ from the saved run's "
                         f"({', '.join(f'{n}={before.get(n)!r}' for n in changed)})")


def evaluation_score(results: dict[str, dict[str, float]]) -> float:
    """How good a periodic evaluation is, to keep the best weights: the mean over clips of the RSI
    success plus the share of the clip tracked from frame 0 (each in [0, 1])."""
    return float(sum(r["success"] + r["frames"] / r["num_frames"] for r in results.values()) / len(results))


def evaluation_meets(results: dict[str, dict[str, float]], success: float) -> bool:
    """The stop rule: every clip at ``success`` or more from RSI starts and tracked from frame 0
    to its end."""
    return all(r["success"] >= success and r["whole_clip"] for r in results.values())


def evaluation_score_of(checkpoint: dict[str, Any]) -> float:
    """:func:`evaluation_score` of the evaluation a checkpoint was saved at (from its run's log)."""
    return float(checkpoint.get("evaluation_score", -math.inf))
