"""Rendering: offscreen images of the humanoid (with its reference as a translucent ghost, or a
batch of simulations one image each), and MuJoCo's interactive viewer for ``render_mode="human"``."""

from __future__ import annotations

import os
import sys

import mujoco
import numpy as np


class GhostRenderer:
    """Renders ``data`` and overlays the humanoid posed at a reference ``qpos``.

    Headless: importing :mod:`crisp_gym` selects ``MUJOCO_GL=egl`` when there is no display
    (set ``MUJOCO_GL=osmesa`` before importing where EGL is missing).
    """

    def __init__(self, model: mujoco.MjModel, width: int = 640, height: int = 480,
                 ghost_rgba: tuple[float, float, float, float] = (0.3, 0.9, 0.4, 0.35)):
        self.model = model
        self.renderer = mujoco.Renderer(model, height, width)
        self.ghost = mujoco.MjData(model)
        self.ghost_rgba = np.asarray(ghost_rgba, dtype=np.float32)
        self.option = mujoco.MjvOption()
        self.perturb = mujoco.MjvPerturb()
        # Only the humanoid's (dynamic) geoms are drawn for the ghost, not the scene again.
        self.option.geomgroup[:] = 1

    def render(self, data: mujoco.MjData, ghost_qpos: np.ndarray | None = None, camera: str = "follow") -> np.ndarray:
        self.renderer.update_scene(data, camera=camera)
        if ghost_qpos is not None:
            self.ghost.qpos[:] = ghost_qpos
            mujoco.mj_kinematics(self.model, self.ghost)
            scene = self.renderer.scene
            start = scene.ngeom
            mujoco.mjv_addGeoms(self.model, self.ghost, self.option, self.perturb,
                                mujoco.mjtCatBit.mjCAT_DYNAMIC, scene)
            for i in range(start, scene.ngeom):
                scene.geoms[i].rgba[:] = self.ghost_rgba
        return self.renderer.render()

    def close(self) -> None:
        self.renderer.close()


def has_display() -> bool:
    """Whether a window can open: always on macOS and Windows, with X11 or Wayland on Linux."""
    return sys.platform != "linux" or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class HumanViewer:
    """MuJoCo's own interactive viewer (``mujoco.viewer.launch_passive``) following ``data``:
    ``render_mode="human"``. It opens a window, so it needs a display; MuJoCo's GLFW ends the
    whole process when there is none, hence the check first."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData):
        if not has_display():
            raise RuntimeError("render_mode='human' opens MuJoCo's viewer window and needs a display (no DISPLAY "
                               "or WAYLAND_DISPLAY here); use render_mode='rgb_array' for frames or videos")
        import mujoco.viewer  # noqa: PLC0415 - loads GLFW

        self.handle = mujoco.viewer.launch_passive(model, data, show_left_ui=False, show_right_ui=False)

    def sync(self) -> None:
        """Show the data's current state (the viewer reads it; MuJoCo recommends its lock)."""
        with self.handle.lock():
            self.handle.sync()

    def close(self) -> None:
        self.handle.close()


def render_states(renderer: mujoco.Renderer, model: mujoco.MjModel, scratch: mujoco.MjData, qpos: np.ndarray,
                  qvel: np.ndarray, camera: str = "follow") -> tuple[np.ndarray, ...]:
    """One image per row of ``qpos``/``qvel`` (a batch of simulations of ``model``), each posed in
    ``scratch`` and drawn by ``renderer`` from ``camera``."""
    images = []
    for q, v in zip(qpos, qvel):
        scratch.qpos[:], scratch.qvel[:] = q, v
        mujoco.mj_forward(model, scratch)
        renderer.update_scene(scratch, camera=camera)
        images.append(renderer.render())
    return tuple(images)
