"""Policy and value networks for ``CrispTrack-v0`` (paper, Sec. 3.4 and App. "RL training details").

Every module here is plain torch: it takes the observation tensors (``proprio`` (…, 361),
``targets`` (…, K, 432) and, scene-aware, ``points`` (…, N, 3)) with any number of leading
batch dimensions and returns tensors. TorchRL wraps them in :mod:`crisp_gym.train.ppo`; a trained
actor is read back from its file by :mod:`crisp_gym.policy.files`.

* :class:`TransformerActor`: the paper's actor. One token from the proprioception, one per
  future target frame and, scene-aware, ``num_point_tokens`` tokens from the point encoder
  (the paper's :class:`PointNet`, or :class:`FlatPoints`); a transformer encoder (latent 256,
  feed-forward 512, 2 layers, 2 heads); mean-pooled tokens → 69 action means.
* :class:`MLPActor`: the same inputs flattened into an MLP of similar size (the CPU profile:
  a PPO epoch costs about a third of the transformer's on two cores).
* :class:`FixedStdGaussian`: actor → (mean, σ) with the paper's fixed σ = 0.055.
* :class:`Critic`: MLP with hidden sizes [1024, 512].
* :class:`ObsNormalizer`: running mean/variance per feature, updated from collected batches;
  its statistics are buffers, so they are saved and loaded with the module's ``state_dict``.

The actor and the critic hold the *same* :class:`ObsNormalizer` instance. Points are not
normalised: they are already metres in the pelvis's heading frame, and the PointNet is
invariant to their order, which per-point statistics would break.

Scene-aware actors are built for a number of points N (``num_points``; 0 means scene-blind): the
PointNet takes any N, :class:`FlatPoints` the N it was built for.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from crisp_gym.envs.tracking import PROPRIO_DIM, TARGET_DIM
from crisp_gym.humanoid import DOF_NAMES
from crisp_gym.policy.model_config import ModelConfig

ACTION_DIM = len(DOF_NAMES)  # one PD target per hinge


class Float32Linear(nn.Linear):
    """A linear layer that computes in float32 even inside ``torch.autocast``.

    The output layers of the actor and the critic: under bfloat16 autocast (training's
    ``precision="bfloat16"``) the hidden layers run in bfloat16, but the action means and the
    values keep float32's precision. bfloat16 keeps 8 significant bits: a value of 10 would be
    rounded by up to 0.04 before GAE differences it into advantages, and an action mean by up
    to 0.4 % before the log-probability divides its distance to the action by σ = 0.055.
    Without autocast it is an ``nn.Linear`` (the same parameters and state-dict keys).
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not torch.is_autocast_enabled(x.device.type):
            return super().forward(x)
        with torch.autocast(x.device.type, enabled=False):
            return super().forward(x.float())


def mlp(in_dim: int, hidden: Sequence[int], out_dim: int | None = None, activation: type[nn.Module] = nn.ELU,
        float32_output: bool = False) -> nn.Sequential:
    """Linear + activation per hidden size, then an optional linear output layer
    (a :class:`Float32Linear` with ``float32_output``)."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(in_dim, width), activation()]
        in_dim = width
    if out_dim is not None:
        layers.append((Float32Linear if float32_output else nn.Linear)(in_dim, out_dim))
    return nn.Sequential(*layers)


class RunningMeanStd(nn.Module):
    """Per-feature running mean and (population) variance of a stream of batches.

    Batches are merged exactly (Chan et al.'s parallel update) in float64, so after any
    sequence of :meth:`update` calls ``mean``/``var`` equal the mean and ``ddof=0`` variance of
    all samples seen. :meth:`forward` returns ``(x - mean) / sqrt(var + eps)`` clipped to
    ``± clip`` in ``x``'s dtype.

    Args:
        shape: feature shape (the trailing dimensions of the inputs).
        eps: added to the variance before the square root.
        clip: bound of the normalised values.
    """

    def __init__(self, shape: int | Sequence[int], eps: float = 1e-5, clip: float = 5.0):
        super().__init__()
        self.shape = torch.Size([shape] if isinstance(shape, int) else shape)
        self.eps = eps
        self.clip = clip
        self.register_buffer("mean", torch.zeros(self.shape, dtype=torch.float64))
        self.register_buffer("var", torch.ones(self.shape, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merge a batch ``x`` (…, *shape) into the statistics (in place)."""
        x = x.detach().reshape(-1, *self.shape).to(torch.float64)
        n = x.shape[0]
        if n == 0:
            return
        batch_mean = x.mean(dim=0)
        batch_var = x.var(dim=0, unbiased=False)
        total = self.count + n
        delta = batch_mean - self.mean
        new_mean = self.mean + delta * (n / total)
        m2 = self.var * self.count + batch_var * n + delta.square() * (self.count * n / total)
        self.mean.copy_(new_mean)
        self.var.copy_(m2 / total)
        self.count.fill_(total)

    @torch.no_grad()
    def limit_count(self, samples: float) -> None:
        """Let the statistics count as at most ``samples`` samples, so later batches move them
        as much as if only that many had been seen (a warm start on different data)."""
        self.count.clamp_(max=float(samples))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean = self.mean.to(x.dtype)
        std = torch.sqrt(self.var + self.eps).to(x.dtype)
        return ((x - mean) / std).clamp(-self.clip, self.clip)


class ObsNormalizer(nn.Module):
    """Running normalisation of ``proprio`` and ``targets`` (per feature; points pass through).

    Args:
        num_targets: K, the future frames in ``targets``.
        clip: bound of the normalised values.
        enabled: ``False`` makes it the identity (and :meth:`update` a no-op).
    """

    def __init__(self, num_targets: int, clip: float = 5.0, enabled: bool = True):
        super().__init__()
        self.enabled = enabled
        self.proprio = RunningMeanStd(PROPRIO_DIM, clip=clip)
        self.targets = RunningMeanStd((num_targets, TARGET_DIM), clip=clip)

    @torch.no_grad()
    def update(self, proprio: torch.Tensor, targets: torch.Tensor) -> None:
        """Merge a batch of observations into the statistics."""
        if self.enabled:
            self.proprio.update(proprio)
            self.targets.update(targets)

    def limit_count(self, samples: float) -> None:
        """:meth:`RunningMeanStd.limit_count` for both statistics."""
        self.proprio.limit_count(samples)
        self.targets.limit_count(samples)

    def forward(self, proprio: torch.Tensor, targets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if not self.enabled:
            return proprio, targets
        return self.proprio(proprio), self.targets(targets)


class PointNet(nn.Module):
    """Shared per-point MLP followed by a max over points: (…, N, 3) → (…, hidden[-1])."""

    def __init__(self, hidden: Sequence[int] = (64, 128, 256)):
        super().__init__()
        self.point_mlp = mlp(3, hidden[:-1], hidden[-1])
        self.out_dim = hidden[-1]

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        # max rather than amax: its backward scatters to the arg-max alone instead of comparing
        # every point with the maximum (the scene-aware update ran 11 % faster end to end)
        return self.point_mlp(points).max(dim=-2).values


class FlatPoints(nn.Module):
    """The points flattened in their order, through one linear layer and an ELU: (…, N, 3) → (…, out_dim).

    The env sorts them nearest the pelvis first, so each slot keeps a meaning; on two CPU cores
    its PPO update costs about what a scene-blind actor's does, where a PointNet over 128 points
    doubled it (a shared MLP per point, then the max).
    """

    def __init__(self, num_points: int, out_dim: int):
        super().__init__()
        if num_points < 1:
            raise ValueError(f"num_points must be at least 1, got {num_points}")
        self.num_points = num_points
        self.linear = nn.Linear(3 * num_points, out_dim)
        self.activation = nn.ELU()
        self.out_dim = out_dim

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        if not torch.jit.is_tracing() and points.shape[-2:] != (self.num_points, 3):  # (traced: shapes are fixed)
            raise ValueError(f"this encoder takes ({self.num_points}, 3) points, got {tuple(points.shape[-2:])}")
        return self.activation(self.linear(points.flatten(-2)))


def point_encoder(config: ModelConfig, num_points: int) -> PointNet | FlatPoints:
    """The scene-aware actors' point encoder named by ``config.point_encoder``."""
    if config.point_encoder == "flat":
        return FlatPoints(num_points, config.pointnet_hidden[-1])
    return PointNet(config.pointnet_hidden)


def _rename_pointnet(module: nn.Module, state_dict: dict, prefix: str, *_) -> None:
    """``register_load_state_dict_pre_hook``: files written before the point encoder was
    configurable call it ``pointnet``."""
    old = prefix + "pointnet."
    for key in [k for k in state_dict if k.startswith(old)]:
        state_dict[prefix + "point_encoder." + key[len(old):]] = state_dict.pop(key)


def _flatten_batch(x: torch.Tensor, feature_dims: int) -> tuple[torch.Tensor, torch.Size]:
    """Collapse the leading batch dimensions of ``x`` into one; returns them for restoring."""
    batch = x.shape[: x.dim() - feature_dims]
    return x.reshape(-1, *x.shape[x.dim() - feature_dims:]), batch


def _check_points(scene_aware: bool, points: torch.Tensor | None) -> None:
    if scene_aware and points is None:
        raise ValueError("this network is scene-aware: pass the 'points' observation")


def _flat_features(normalizer: ObsNormalizer, scene_aware: bool, proprio: torch.Tensor, targets: torch.Tensor,
                   points: torch.Tensor | None) -> list[torch.Tensor]:
    """[normalised proprio, normalised targets flattened], the MLPs' inputs before the points."""
    _check_points(scene_aware, points)
    proprio, targets = normalizer(proprio, targets)
    return [proprio, targets.flatten(-2)]


class TransformerActor(nn.Module):
    """The paper's transformer actor: observation tokens → encoder → mean pool → action means.

    Tokens: ``proprio`` → 1 token; each of the K ``targets`` frames → 1 token (a shared
    projection plus a learned per-frame embedding); scene-aware, the PointNet feature →
    ``num_point_tokens`` tokens. Every token also gets a learned type embedding.

    Args:
        num_targets: K.
        num_points: N, the ``points`` it expects; 0: scene-blind.
        normalizer: the shared observation normaliser.
        config: architecture.
    """

    def __init__(self, num_targets: int, num_points: int, normalizer: ObsNormalizer,
                 config: ModelConfig = ModelConfig()):
        super().__init__()
        d = config.latent_dim
        self.scene_aware = scene_aware = num_points > 0
        self.normalizer = normalizer
        self.num_point_tokens = config.num_point_tokens
        self.proprio_embed = nn.Linear(PROPRIO_DIM, d)
        self.target_embed = nn.Linear(TARGET_DIM, d)
        self.frame_embed = nn.Parameter(torch.zeros(num_targets, d))
        num_types = 3 if scene_aware else 2
        self.type_embed = nn.Parameter(torch.zeros(num_types, d))
        if scene_aware:
            self.point_encoder = point_encoder(config, num_points)
            self.point_embed = nn.Linear(self.point_encoder.out_dim, d * config.num_point_tokens)
            self.register_load_state_dict_pre_hook(_rename_pointnet)
        layer = nn.TransformerEncoderLayer(d, config.num_heads, config.ff_dim, dropout=0.0, activation="gelu",
                                           batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, config.num_layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(d)
        self.action_head = Float32Linear(d, ACTION_DIM)
        nn.init.normal_(self.frame_embed, std=0.02)
        nn.init.normal_(self.type_embed, std=0.02)
        nn.init.normal_(self.action_head.weight, std=config.init_action_std)
        nn.init.zeros_(self.action_head.bias)

    def tokens(self, proprio: torch.Tensor, targets: torch.Tensor,
               points: torch.Tensor | None = None) -> torch.Tensor:
        """(B, T, latent) input tokens for flattened batches."""
        proprio, targets = self.normalizer(proprio, targets)
        tokens = [self.proprio_embed(proprio)[:, None] + self.type_embed[0],
                  self.target_embed(targets) + self.frame_embed + self.type_embed[1]]
        if self.scene_aware:
            feature = self.point_embed(self.point_encoder(points))
            tokens.append(feature.reshape(feature.shape[0], self.num_point_tokens, -1) + self.type_embed[2])
        return torch.cat(tokens, dim=1)

    def forward(self, proprio: torch.Tensor, targets: torch.Tensor,
                points: torch.Tensor | None = None) -> torch.Tensor:
        """Action means (…, 69)."""
        _check_points(self.scene_aware, points)
        proprio, batch = _flatten_batch(proprio, 1)
        targets, _ = _flatten_batch(targets, 2)
        if self.scene_aware:
            points, _ = _flatten_batch(points, 2)
        encoded = self.encoder(self.tokens(proprio, targets, points))
        return self.action_head(self.norm(encoded.mean(dim=1))).reshape(*batch, ACTION_DIM)


class MLPActor(nn.Module):
    """MLP actor: normalised ``proprio`` and flattened ``targets`` (+ a point feature) → action means.

    Args:
        num_targets: K.
        num_points: N, the ``points`` it expects (encoded by :func:`point_encoder`); 0: scene-blind.
        normalizer: the shared observation normaliser.
        config: architecture (``mlp_actor_hidden``, ``point_encoder``, ``pointnet_hidden``).
    """

    def __init__(self, num_targets: int, num_points: int, normalizer: ObsNormalizer,
                 config: ModelConfig = ModelConfig()):
        super().__init__()
        self.scene_aware = num_points > 0
        self.normalizer = normalizer
        in_dim = PROPRIO_DIM + num_targets * TARGET_DIM
        if self.scene_aware:
            self.point_encoder = point_encoder(config, num_points)
            in_dim += self.point_encoder.out_dim
            self.register_load_state_dict_pre_hook(_rename_pointnet)
        self.net = mlp(in_dim, config.mlp_actor_hidden, ACTION_DIM, float32_output=True)
        head = self.net[-1]
        nn.init.normal_(head.weight, std=config.init_action_std)
        nn.init.zeros_(head.bias)

    def forward(self, proprio: torch.Tensor, targets: torch.Tensor,
                points: torch.Tensor | None = None) -> torch.Tensor:
        """Action means (…, 69)."""
        features = _flat_features(self.normalizer, self.scene_aware, proprio, targets, points)
        if self.scene_aware:
            features.append(self.point_encoder(points))
        return self.net(torch.cat(features, dim=-1))

    @property
    def action_head(self) -> nn.Linear:
        return self.net[-1]


class FixedStdGaussian(nn.Module):
    """Wraps an actor into the parameters of a diagonal Gaussian with a fixed σ.

    ``forward`` returns ``(loc, scale)``; ``scale`` is a constant (not learned), as in the
    paper (σ = 0.055).
    """

    def __init__(self, actor: nn.Module, std: float = 0.055):
        super().__init__()
        self.actor = actor
        self.register_buffer("std", torch.tensor(float(std)))

    def forward(self, proprio: torch.Tensor, targets: torch.Tensor,
                points: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        loc = self.actor(proprio, targets, points)
        return loc, self.std.expand_as(loc)


class Critic(nn.Module):
    """MLP value function on normalised ``proprio``, flattened ``targets`` and flattened ``points``.

    Args:
        num_targets: K.
        num_points: N (scene-aware), or 0.
        normalizer: the shared observation normaliser.
        hidden: hidden sizes (paper: [1024, 512]).
    """

    def __init__(self, num_targets: int, num_points: int, normalizer: ObsNormalizer,
                 hidden: Sequence[int] = (1024, 512)):
        super().__init__()
        self.scene_aware = num_points > 0
        self.normalizer = normalizer
        self.net = mlp(PROPRIO_DIM + num_targets * TARGET_DIM + 3 * num_points, hidden, 1, float32_output=True)

    def forward(self, proprio: torch.Tensor, targets: torch.Tensor,
                points: torch.Tensor | None = None) -> torch.Tensor:
        """State values (…, 1)."""
        features = _flat_features(self.normalizer, self.scene_aware, proprio, targets, points)
        if self.scene_aware:
            features.append(points.flatten(-2))
        return self.net(torch.cat(features, dim=-1))


def build_actor(config: ModelConfig, num_targets: int, num_points: int,
                normalizer: ObsNormalizer) -> TransformerActor | MLPActor:
    """The actor named by ``config.actor``, for ``num_points`` points (0: scene-blind)."""
    cls = TransformerActor if config.actor == "transformer" else MLPActor
    return cls(num_targets, num_points, normalizer, config)
