"""The architecture of a policy's networks as plain values (:class:`ModelConfig`).

Apart from :mod:`crisp_gym.policy.networks`, which builds the networks, so that reading or
writing a configuration (``crisp train --help``, a run's ``config.json``) never imports torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of the actor and the critic; the defaults are the paper's.

    Attributes:
        actor: "transformer" (the paper's) or "mlp".
        latent_dim: transformer token width.
        ff_dim: transformer feed-forward width.
        num_layers: transformer encoder layers.
        num_heads: self-attention heads.
        num_point_tokens: tokens the point feature is projected to (scene-aware only).
        point_encoder: how a scene-aware actor encodes the points: "pointnet" (the paper's) or
            "flat" (FlatPoints in crisp_gym.policy.networks: one linear layer over the points
            nearest first, a fraction of a PointNet's cost in the PPO update).
        pointnet_hidden: widths of the PointNet's shared per-point MLP (the last one is the
            pooled feature size, also the flat encoder's feature size).
        mlp_actor_hidden: hidden sizes of the MLP actor.
        critic_hidden: hidden sizes of the critic (paper: [1024, 512]).
        action_std: the Gaussian policy's fixed standard deviation (paper: 0.055).
        obs_clip: normalised observations are clipped to ± this.
        init_action_std: standard deviation of the action head's initial weights; small, so the
            untrained policy's residual actions start near zero (track the reference pose).
    """

    actor: str = "transformer"
    latent_dim: int = 256
    ff_dim: int = 512
    num_layers: int = 2
    num_heads: int = 2
    num_point_tokens: int = 1
    point_encoder: str = "pointnet"
    pointnet_hidden: tuple[int, ...] = (64, 128, 256)
    mlp_actor_hidden: tuple[int, ...] = (512, 512)
    critic_hidden: tuple[int, ...] = (1024, 512)
    action_std: float = 0.055
    obs_clip: float = 5.0
    init_action_std: float = 0.001

    def __post_init__(self) -> None:
        if self.actor not in ("transformer", "mlp"):
            raise ValueError(f"actor must be 'transformer' or 'mlp', got {self.actor!r}")
        if self.point_encoder not in ("pointnet", "flat"):
            raise ValueError(f"point_encoder must be 'pointnet' or 'flat', got {self.point_encoder!r}")
        if self.latent_dim % self.num_heads:
            raise ValueError(f"latent_dim ({self.latent_dim}) must be divisible by num_heads ({self.num_heads})")
        if self.action_std <= 0 or self.obs_clip <= 0:
            raise ValueError("action_std and obs_clip must be positive")
        if self.num_point_tokens < 1 or not self.pointnet_hidden:
            raise ValueError("num_point_tokens must be at least 1 and pointnet_hidden non-empty")


def model_config(config: dict[str, Any]) -> ModelConfig:
    """The :class:`ModelConfig` of a saved training config (JSON keeps tuples as lists)."""
    return ModelConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in config["model"].items()})
