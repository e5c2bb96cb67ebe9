"""PPO training of tracking policies for ``CrispTrack-v0`` on TorchRL components.

* :mod:`train.models`: the paper's transformer actor (and an MLP actor for CPUs), the MLP
  critic, the PointNet scene encoder and the running observation normaliser.
* :mod:`train.env`: a native TorchRL ``EnvBase`` around the batched ``CrispTrack-v0``.
* :mod:`train.ppo`: :class:`~train.ppo.TrainConfig`, :func:`~train.ppo.train` and the CLI
  entry point :func:`~train.ppo.main`.
* :mod:`train.evaluate`: ``crisp eval``: deterministic roll-outs of a policy, success rates,
  W-/WA-MPJPE, jitter, acceleration error, plots and video.
* :mod:`train.ship`: packages a run (policy file, log, learning curve, evaluation) for
  ``assets/policies``.

Only :mod:`train.ppo` and :mod:`train.env` import TorchRL; the models are plain torch.
"""

from train.models import (
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
