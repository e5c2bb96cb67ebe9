"""PPO training of tracking policies for ``CrispTrack-v0`` on TorchRL components.

* :mod:`crisp_gym.train.ppo`: the algorithm, read top to bottom (:func:`~crisp_gym.train.ppo.train`);
  around it :mod:`~crisp_gym.train.config` (``TrainConfig`` and its profiles),
  :mod:`~crisp_gym.train.checkpoints`, :mod:`~crisp_gym.train.run_log` (``progress.csv`` and
  experiment loggers) and :mod:`~crisp_gym.train.cli` (``crisp train``).
* :mod:`crisp_gym.train.env`: a native TorchRL ``EnvBase`` around the batched ``CrispTrack-v0``.
* :mod:`crisp_gym.train.evaluate`: ``crisp eval``: deterministic roll-outs of a policy, success rates,
  W-/WA-MPJPE, jitter, acceleration error, plots and video.
* :mod:`crisp_gym.train.ship`: packages a run (policy file, log, learning curve, evaluation) for
  ``assets/policies``.
* :mod:`crisp_gym.train.demo`: ``crisp demo``, a shipped policy on a bundled clip.

The networks and the policy files are below this package, in :mod:`crisp_gym.policy`. Only
:mod:`crisp_gym.train.ppo` and :mod:`crisp_gym.train.env` import TorchRL.
"""
