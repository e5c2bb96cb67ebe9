"""What a user looks at after ``crisp reconstruct VIDEO``: the input beside the reconstruction.

Each frame of ``comparison.mp4`` is the input frame (left) and, seen from the camera the video
was shot from (its estimated pose and focal length), the reconstructed boxes with the reference
humanoid posed at the same instant (right). Where the two disagree, the reconstruction is wrong.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import imageio
import mujoco
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from crisp_gym.atomic import atomic_path
from crisp_gym.envs.tracking import build_track_spec
from crisp_gym.reconstruct.video import VideoReconstruction

_OPENCV_TO_MUJOCO = np.diag([1.0, -1.0, -1.0])  # OpenCV cameras look down +z with y down; MuJoCo's down -z, y up


def write_comparison(result: VideoReconstruction, frames: np.ndarray, fps: float, path: str | Path,
                     height: int = 480, progress: bool = True) -> Path:
    """Write the side-by-side video (see the module docstring); returns its path."""
    spec = build_track_spec(result.boxes, timestep=1.0 / 120.0)
    spec.worldbody.add_camera(name="input_view", pos=(0.0, 0.0, 0.0))
    model = spec.compile()
    data = mujoco.MjData(model)
    camera = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "input_view")
    image_h, image_w = frames.shape[1:3]
    focal = result.cameras.intrinsic[1, 1]
    model.cam_fovy[camera] = np.rad2deg(2 * np.arctan(image_h / (2 * focal)))
    width = int(round(height * image_w / image_h))
    renderer = mujoco.Renderer(model, height, width)
    poses = result.camera_in_world()
    qpos = result.motion.qpos()
    try:
        with atomic_path(path) as tmp, imageio.get_writer(tmp, fps=fps, macro_block_size=8) as writer:
            for k in tqdm(range(len(frames)), desc="comparison video", unit="frame", disable=not progress):
                data.qpos[: qpos.shape[1]] = qpos[min(int(round(k / fps * result.motion.fps)), len(qpos) - 1)]
                model.cam_pos[camera] = poses[k, :3, 3]
                rotation = poses[k, :3, :3] @ _OPENCV_TO_MUJOCO
                model.cam_quat[camera] = Rotation.from_matrix(rotation).as_quat(scalar_first=True)
                mujoco.mj_forward(model, data)
                renderer.update_scene(data, camera=camera)
                left = cv2.resize(frames[k], (width, height), interpolation=cv2.INTER_AREA)
                writer.append_data(np.hstack([left, renderer.render()]))
    finally:
        renderer.close()
    return Path(path)
