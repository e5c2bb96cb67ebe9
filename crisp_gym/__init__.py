"""crisp-gym: videos of people in their surroundings → MuJoCo worlds and humanoids that re-enact them.

Importing the package registers ``CrispTrack-v0`` with Gymnasium (single env and, via
``gym.make_vec(..., vectorization_mode="vector_entry_point")``, the batched env).
"""

import os

# Headless machines have no display for GLFW; MuJoCo reads MUJOCO_GL when it is imported,
# so the offscreen backend must be chosen here, before anything imports mujoco.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"

import gymnasium as gym  # noqa: E402

__version__ = "0.1.0"

if "CrispTrack-v0" not in gym.registry:
    gym.register(
        id="CrispTrack-v0",
        entry_point="crisp_gym.envs.track:CrispTrackEnv",
        vector_entry_point="crisp_gym.envs.track_vector:make_vector_env",
    )
