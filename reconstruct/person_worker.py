"""MediaPipe Pose over a stack of RGB frames, run in its own process by :mod:`crisp_gym.reconstruct.person`.

Usage: ``python -m crisp_gym.reconstruct.person_worker FRAMES.npy OUT.npz``. Imports only numpy, OpenCV
and MediaPipe: MediaPipe 0.10.21 (the last release that ships its pose and segmentation models
inside the wheel, so nothing is downloaded) needs protobuf < 5, while onnx in the same
environment needs protobuf >= 6, so :mod:`crisp_gym.reconstruct.person` puts a private protobuf first on
this process's path. One line per 10 frames on stdout (``done total``) drives the caller's
progress bar.
"""

from __future__ import annotations

import sys

import numpy as np


def main(frames_path: str, out_path: str) -> None:
    import mediapipe as mp  # noqa: PLC0415 - only importable with the private runtime on the path

    frames = np.load(frames_path, mmap_mode="r")
    t, h, w = frames.shape[:3]
    image = np.full((t, 33, 3), np.nan)
    world = np.full((t, 33, 3), np.nan)
    visibility = np.zeros((t, 33))
    masks = np.zeros((t, h, w), dtype=np.uint8)
    # model_complexity=1 is the model inside the wheel (0 and 2 are downloaded on first use).
    with mp.solutions.pose.Pose(static_image_mode=False, model_complexity=1, enable_segmentation=True,
                                smooth_landmarks=True, smooth_segmentation=True) as pose:
        for k in range(t):
            result = pose.process(np.ascontiguousarray(frames[k]))
            if result.pose_landmarks is not None:
                marks = result.pose_landmarks.landmark
                image[k] = [(p.x * w, p.y * h, p.z * w) for p in marks]
                visibility[k] = [p.visibility for p in marks]
                world[k] = [(p.x, p.y, p.z) for p in result.pose_world_landmarks.landmark]
                masks[k] = np.asarray(result.segmentation_mask) > 0.5
            if (k + 1) % 10 == 0 or k + 1 == t:
                print(k + 1, t, flush=True)
    np.savez_compressed(out_path, image=image, world=world, visibility=visibility, masks=masks)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python -m crisp_gym.reconstruct.person_worker FRAMES.npy OUT.npz")
    main(sys.argv[1], sys.argv[2])
