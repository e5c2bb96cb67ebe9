"""Rendering: how a composed model looks (:func:`style_scene`), offscreen images of the humanoid
(with its reference as a translucent ghost), and what an env's ``render()`` shows
(:class:`EnvDisplay`: images, or MuJoCo's interactive viewer for ``render_mode="human"``)."""

from __future__ import annotations

import os
import sys

import mujoco
import numpy as np

SKY = ((0.62, 0.76, 0.92), (0.16, 0.22, 0.34))
"""Skybox gradient, horizon to zenith."""
CHECKER = ((0.80, 0.80, 0.78), (0.66, 0.66, 0.64))
"""The floor's checker squares (0.5 m)."""


def style_scene(spec: mujoco.MjSpec) -> None:
    """Dress a composed model as MuJoCo's own demos are: a gradient sky, a checkered floor (every
    geom named ``floor``, also a motion library's ``clip3/floor``), soft light and fine shadows.
    Only how it looks changes: no mass, contact or solver setting."""
    spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX, builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
                     rgb1=SKY[0], rgb2=SKY[1], width=512, height=3072)
    spec.add_texture(name="checker", type=mujoco.mjtTexture.mjTEXTURE_2D,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER, rgb1=CHECKER[0], rgb2=CHECKER[1],
                     width=512, height=512)
    floor = spec.add_material(name="floor", texrepeat=(2.0, 2.0), texuniform=True, reflectance=0.05)
    floor.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "checker"
    for geom in spec.geoms:
        if geom.name == "floor" or geom.name.endswith("/floor"):
            geom.material = "floor"
            geom.rgba = (1.0, 1.0, 1.0, 1.0)
    spec.visual.quality.shadowsize = 4096
    # a directional light's shadow map spans the model's extent, which a 40 m floor makes coarse:
    # the clips' action is within a few metres of the origin
    spec.stat.extent = 6.0
    spec.visual.headlight.ambient = (0.35, 0.35, 0.35)
    spec.visual.headlight.diffuse = (0.45, 0.45, 0.45)
    spec.visual.headlight.specular = (0.1, 0.1, 0.1)


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


class EnvDisplay:
    """What an env's ``render()`` shows for its ``render_mode``: ``"rgb_array"`` images from the
    ``follow`` camera, or ``"human"`` MuJoCo's viewer window; made on first use, closed with the env."""

    def __init__(self, model: mujoco.MjModel, mode: str | None, width: int, height: int):
        self.model, self.mode, self.size = model, mode, (height, width)
        self._renderer: mujoco.Renderer | None = None
        self._viewer: HumanViewer | None = None

    def show(self, data: mujoco.MjData) -> np.ndarray | None:
        """The image of ``data`` (``rgb_array``), or ``None`` after syncing the viewer (``human``)."""
        if self.mode == "human":
            if self._viewer is None:
                self._viewer = HumanViewer(self.model, data)
            self._viewer.sync()
            return None
        if self.mode != "rgb_array":
            return None
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, *self.size)
        self._renderer.update_scene(data, camera="follow")
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None
