"""PPO training of tracking policies for ``CrispTrack-v0`` on TorchRL components.

* :mod:`crisp_gym.train.models`: the paper's transformer actor (and an MLP actor for CPUs), the MLP
  critic, the PointNet scene encoder and the running observation normaliser.
* :mod:`crisp_gym.train.env`: a native TorchRL ``EnvBase`` around the batched ``CrispTrack-v0``.
* :mod:`crisp_gym.train.ppo`: :class:`~crisp_gym.train.ppo.TrainConfig`, :func:`~crisp_gym.train.ppo.train` and the CLI
  entry point :func:`~crisp_gym.train.ppo.main`.
* :mod:`crisp_gym.train.evaluate`: ``crisp eval``: deterministic roll-outs of a policy, success rates,
  W-/WA-MPJPE, jitter, acceleration error, plots and video.
* :mod:`crisp_gym.train.ship`: packages a run (policy file, log, learning curve, evaluation) for
  ``assets/policies``.

Only :mod:`crisp_gym.train.ppo` and :mod:`crisp_gym.train.env` import TorchRL; the models are plain torch.
"""

from crisp_gym.train.models import (
    Critic,
    FixedStdGaussian,
    MLPActor,
    ModelConfig,
    ObsNormalizer,
    PointNet,
    RunningMeanStd,
    TransformerActor,
    build_actor,
)

__all__ = [
    "Critic",
    "FixedStdGaussian",
    "MLPActor",
    "ModelConfig",
    "ObsNormalizer",
    "PointNet",
    "RunningMeanStd",
    "TransformerActor",
    "build_actor",
]
