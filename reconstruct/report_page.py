"""The page of a reconstruction, ``report.html`` in the clip folder: its numbers, a picture of the
clip (the scene and the humanoid at the motion's middle frame, from the env's follow camera) and,
for a plain video, the input beside the reconstruction (``comparison.mp4``)."""

from __future__ import annotations

import logging
from pathlib import Path

import imageio.v3 as iio
import mujoco

from crisp_gym.envs.tracking import build_track_model
from crisp_gym.html_report import Section, rows_from, write_html_report
from crisp_gym.motion import Motion
from crisp_gym.scene import Box

log = logging.getLogger(__name__)

PICTURE = "clip.png"


def write_clip_picture(boxes: list[Box], motion: Motion, path: Path, width: int = 640, height: int = 480) -> bool:
    """Render the clip into ``path``; False (with a warning) where there is no OpenGL to render with,
    since a reconstruction must not fail for a picture."""
    model = build_track_model(boxes, 1.0 / 120.0)
    data = mujoco.MjData(model)
    data.qpos[:] = motion.qpos()[motion.num_frames // 2]
    mujoco.mj_forward(model, data)
    try:
        renderer = mujoco.Renderer(model, height, width)
    except Exception as err:  # noqa: BLE001 - no display, EGL or OSMesa: anything the GL backend raises
        log.warning("no picture of the clip in report.html: cannot render here (%s)", err)
        return False
    try:
        renderer.update_scene(data, camera="follow")
        iio.imwrite(path, renderer.render())
    finally:
        renderer.close()
    return True


def write_report_page(directory: Path, meta: dict, boxes: list[Box], motion: Motion | None,
                      video: str | None = None) -> Path:
    """``report.html`` (and the clip's picture) in ``directory``, a clip folder being written."""
    if motion is not None:
        write_clip_picture(boxes, motion, directory / PICTURE)
    sections = [Section("The clip", figures=(PICTURE,))]
    if video is not None:
        sections.append(Section("The input beside the reconstruction, from the estimated camera", videos=(video,)))
    # wall-clock timings stay in meta.json: the page of a rerun is the same page
    numbers = {k: v for k, v in meta.items() if not k.endswith("timings")}
    sections.append(Section("Numbers (meta.json, without its timings)", rows=rows_from(numbers)))
    return write_html_report(directory / "report.html", f"Reconstruction: {meta.get('name', directory.name)}",
                             sections, subtitle="crisp reconstruct")
