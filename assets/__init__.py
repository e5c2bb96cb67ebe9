"""Package data of crisp-gym (installed as ``crisp_gym.assets``); see :mod:`crisp_gym.bundled`."""
