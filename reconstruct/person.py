"""The person in a plain video: MediaPipe Pose landmarks (2D and metric 3D) and a mask per frame.

MediaPipe 0.10.21 is the last release whose wheel holds its pose and segmentation models (newer
ones download them on first use, which this project never does). It needs protobuf < 5, and the
test and export extras' onnx needs protobuf >= 6, so both cannot share one environment. It is
installed instead into a private folder (:func:`runtime_dir`, by :func:`install_runtime` or
``python -m crisp_gym.reconstruct.person --install``, which ``scripts/install.sh`` runs) and the tracking
runs in a child process with that folder first on its path (:mod:`crisp_gym.reconstruct.person_worker`).
Its wheel declares ``numpy<2``; it runs on numpy 2 (measured: same landmarks), so only
MediaPipe itself and a protobuf 4 go into the folder.

The 33 landmarks are MediaPipe's (:data:`LANDMARKS`); ``world`` landmarks are in metres, centred
between the hips, in axes parallel to the camera's for a person facing it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import platformdirs
from tqdm import tqdm

from crisp_gym.atomic import atomic_directory

MEDIAPIPE_VERSION = "0.10.21"
PROTOBUF_REQUIREMENT = "protobuf>=4.25.3,<5"

LANDMARKS: tuple[str, ...] = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye", "right_eye_outer",
    "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder", "right_shoulder", "left_elbow",
    "right_elbow", "left_wrist", "right_wrist", "left_pinky", "right_pinky", "left_index", "right_index",
    "left_thumb", "right_thumb", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_heel", "right_heel", "left_foot_index", "right_foot_index",
)  # fmt: skip
"""MediaPipe Pose's 33 landmarks, in its order."""


def landmark(name: str) -> int:
    """Index of a MediaPipe landmark by name (e.g. ``"left_ankle"``)."""
    return LANDMARKS.index(name)


@dataclass(frozen=True)
class PersonTrack:
    """The person in each frame (NaN landmarks where nobody was found).

    Attributes:
        image: (T, 33, 2) landmark pixels (x right, y down).
        world: (T, 33, 3) metric landmarks centred between the hips (MediaPipe's world landmarks).
        visibility: (T, 33) MediaPipe's visibility score in [0, 1].
        masks: (T, H, W) bool, the person's pixels.
    """

    image: np.ndarray
    world: np.ndarray
    visibility: np.ndarray
    masks: np.ndarray

    @property
    def found(self) -> np.ndarray:
        """(T,) bool: a person was found in the frame."""
        return np.isfinite(self.image[:, 0, 0])


def runtime_dir() -> Path:
    """The private folder MediaPipe and its protobuf are installed into."""
    return Path(platformdirs.user_data_dir("crisp-gym")) / f"mediapipe-{MEDIAPIPE_VERSION}"


def runtime_installed() -> bool:
    return (runtime_dir() / "mediapipe" / "__init__.py").exists()


def install_runtime(force: bool = False) -> Path:
    """Install MediaPipe 0.10.21 and protobuf 4 into :func:`runtime_dir` (atomically; pip, no deps)."""
    target = runtime_dir()
    if runtime_installed() and not force:
        return target
    with atomic_directory(target, overwrite=True) as tmp:
        subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(tmp),
                        f"mediapipe=={MEDIAPIPE_VERSION}", PROTOBUF_REQUIREMENT], check=True)
    return target


def _missing_runtime_message() -> str:
    return (f"the video path needs MediaPipe {MEDIAPIPE_VERSION} in its private folder {runtime_dir()}: run "
            f"`python -m crisp_gym.reconstruct.person --install` (or scripts/install.sh), and `pip install crisp-gym[video]`")


def track_person(frames: np.ndarray, progress: bool = True) -> PersonTrack:
    """MediaPipe Pose over ``frames`` ((T, H, W, 3) uint8 RGB, in order: it tracks between frames)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be (T, H, W, 3) uint8 RGB, got {frames.shape} {frames.dtype}")
    if not runtime_installed():
        raise FileNotFoundError(_missing_runtime_message())
    with tempfile.TemporaryDirectory(prefix="crisp-person-") as tmp:
        frames_path, out_path = Path(tmp) / "frames.npy", Path(tmp) / "person.npz"
        np.save(frames_path, frames)
        env = _worker_env()
        command = [sys.executable, "-m", "crisp_gym.reconstruct.person_worker", str(frames_path), str(out_path)]
        with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) as proc, \
                tqdm(total=len(frames), desc="person", unit="frame", disable=not progress) as bar:
            for line in proc.stdout:
                done = line.split()[:1]
                if done and done[0].isdigit():
                    bar.n = int(done[0])
                    bar.refresh()
            errors = proc.stderr.read()
        if proc.returncode != 0:
            raise RuntimeError(f"MediaPipe Pose failed (exit {proc.returncode}): {errors.strip()[-2000:]}")
        data = np.load(out_path)
        return PersonTrack(image=data["image"][..., :2], world=data["world"], visibility=data["visibility"],
                           masks=data["masks"].astype(bool))


def _worker_env() -> dict[str, str]:
    env = dict(os.environ)
    paths = [str(runtime_dir())]
    if env.get("PYTHONPATH"):
        paths.append(env["PYTHONPATH"])
    env["PYTHONPATH"] = os.pathsep.join(paths)
    env.setdefault("GLOG_minloglevel", "2")  # MediaPipe's C++ info lines
    env.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    return env


if __name__ == "__main__":
    if sys.argv[1:] != ["--install"]:
        sys.exit("usage: python -m crisp_gym.reconstruct.person --install")
    print(f"MediaPipe {MEDIAPIPE_VERSION} in {install_runtime()}")
