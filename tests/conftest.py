"""Shared fixtures: small clips made by the tests themselves, and the real-data folder."""

from __future__ import annotations

import os
from pathlib import Path

if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from crisp_gym.clip import write_clip  # noqa: E402
from crisp_gym.humanoid import DOF_NAMES, build_humanoid  # noqa: E402
from crisp_gym.motion import Motion, ground  # noqa: E402
from crisp_gym.scene import Box, floor_box  # noqa: E402
from crisp_gym.synth.truth import write_synth_input
from crisp_gym.synth.video import SynthSpec, SynthVideoConfig, render_synth_video  # noqa: E402

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(autouse=True)
def _isolated_user_registry(tmp_path_factory, monkeypatch):
    """Never touch the real user registry from a test."""
    monkeypatch.setenv("CRISP_GYM_USER_REGISTRY", str(tmp_path_factory.mktemp("registry") / "registry.yaml"))


def fold_leg(dof_pos: np.ndarray, side: str, lift: float | np.ndarray) -> None:
    """Fold the ``side`` (``"L"``/``"R"``) leg of (T, 69) hinge angles, in place, by ``lift`` rad
    at the hip and knee and back at the ankle: the foot stays level and rises (3.7 cm at 0.3 rad)."""
    dof_pos[:, DOF_NAMES.index(f"{side}_Hip_y")] = -lift
    dof_pos[:, DOF_NAMES.index(f"{side}_Knee_y")] = 2 * lift
    dof_pos[:, DOF_NAMES.index(f"{side}_Ankle_y")] = -lift


def sway_motion(frames: int = 60, fps: float = 30.0) -> Motion:
    """A slow, kinematically easy motion: walking-pace drift with gentle knee and arm motion."""
    t = np.arange(frames) / fps
    dof = np.zeros((frames, len(DOF_NAMES)))
    dof[:, DOF_NAMES.index("L_Shoulder_x")] = -1.2
    dof[:, DOF_NAMES.index("R_Shoulder_x")] = 1.2
    dof[:, DOF_NAMES.index("L_Knee_y")] = 0.15 * (1 - np.cos(2 * t))
    dof[:, DOF_NAMES.index("L_Hip_y")] = -0.08 * (1 - np.cos(2 * t))
    motion = Motion(fps=fps, root_pos=np.c_[0.1 * t, np.zeros(frames), np.ones(frames)],
                    root_quat=np.tile([1.0, 0, 0, 0], (frames, 1)), dof_pos=dof)
    return ground(motion, build_humanoid())


@pytest.fixture(scope="session")
def sway_clip(tmp_path_factory) -> Path:
    """A clip with a floor and a step box beside the path."""
    path = tmp_path_factory.mktemp("clips") / "sway"
    boxes = [floor_box(), Box(center=[1.0, 0.8, 0.1], half_size=[0.3, 0.3, 0.1])]
    return write_clip(path, boxes, sway_motion(), {"source": "test"})


def small_synth_input(directory: Path, kind: str, seed: int) -> Path:
    """A 160 x 120 synthetic depth video of a ``kind`` clip with its camera-frame motion, written
    as ``crisp reconstruct`` reads it (``input.npz``, ``motion_camera.npz``) into ``directory``."""
    video = render_synth_video(SynthSpec(kind, seed=seed), SynthVideoConfig(width=160, height=120), progress=False)
    return write_synth_input(directory, video)
