"""Offscreen rendering of the simulated humanoid with its reference as a translucent ghost."""

from __future__ import annotations

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
