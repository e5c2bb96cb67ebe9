"""A trained tracking policy: its architecture (:mod:`crisp_gym.policy.model_config`), its networks
(:mod:`crisp_gym.policy.networks`) and its files
(:mod:`crisp_gym.policy.files`: training checkpoints and the small ``policy.pt`` shipped to users).

Below the trainer (:mod:`crisp_gym.train`), so that the demo, ``crisp export`` and the viewer read
policies without importing it.
"""
