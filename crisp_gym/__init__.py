"""crisp-gym: videos of people in their surroundings → MuJoCo worlds and humanoids that re-enact them.

Importing the package registers ``CrispTrack-v0`` with Gymnasium (single env and, via
``gym.make_vec(..., vectorization_mode="vector_entry_point")``, the batched env).
"""

import gymnasium as gym

__version__ = "0.1.0"

if "CrispTrack-v0" not in gym.registry:
    gym.register(
        id="CrispTrack-v0",
        entry_point="crisp_gym.envs.track:CrispTrackEnv",
        vector_entry_point="crisp_gym.envs.track_vector:make_vector_env",
    )
