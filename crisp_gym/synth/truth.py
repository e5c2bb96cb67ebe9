"""A synthetic video on disk: the reconstruction input it plays, and the ground truth next to it
(``gt/`` clip, true cameras, contacts) with the errors of an alignment against it."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crisp_gym.atomic import atomic_directory
from crisp_gym.clip import write_clip
from crisp_gym.motion import Motion
from crisp_gym.reconstruct.io import save_camera_smpl
from crisp_gym.scene import Box, load_primitives
from crisp_gym.synth.video import SynthVideo


def write_synth_input(directory: str | Path, video: SynthVideo, overwrite: bool = False) -> Path:
    """Write ``video`` as ``input.npz``, ``motion_camera.npz`` and ``gt/`` (see the module docstring).

    The directory is built under a temporary name and renamed into place, so an interrupted
    write never leaves a half-written input.
    """
    directory = Path(directory)
    with atomic_directory(directory, overwrite) as tmp:
        frames = video.frames
        float16 = bool(video.meta.get("config", {}).get("noise", {}).get("float16", False))
        with open(tmp / "input.npz", "wb") as f:
            np.savez_compressed(f, depths=frames.depth.astype(np.float16 if float16 else np.float32),
                                intrinsic=frames.intrinsic, cam_c2w=frames.cam_c2w, images=frames.rgb,
                                masks=frames.person_mask.astype(np.uint8), fps=np.float64(frames.fps))
        save_camera_smpl(video.motion_camera, tmp / "motion_camera.npz")
        gt = write_clip(tmp / "gt", video.boxes, video.motion, video.meta)
        np.savez(gt / "cameras.npz", cam_c2w=video.cam_c2w, world_from_input=video.world_from_input,
                 scale=np.float64(video.scale), intrinsic=frames.intrinsic)
        np.savez(gt / "contacts.npz", frame=video.contacts["frame"], body=video.contacts["body"],
                 point=video.contacts["point"], prob=np.ones(len(video.contacts["frame"])))
    return directory


@dataclass(frozen=True)
class SynthTruth:
    """The ground truth of a written synthetic input (``gt/``).

    Attributes:
        boxes: the true scene; motion: the true world motion with contacts.
        cam_c2w: (T, 4, 4) true metric camera poses.
        world_from_input: (4, 4) rigid map from the metric-scaled input frame to the world.
        scale: metric = scale × input.
        contacts: ``frame``, ``body``, ``point``, ``prob`` arrays of ``contacts.npz``.
        meta: ``meta.json``.
    """

    boxes: list[Box]
    motion: Motion
    cam_c2w: np.ndarray
    world_from_input: np.ndarray
    scale: float
    contacts: dict[str, np.ndarray]
    meta: dict


def load_ground_truth(directory: str | Path) -> SynthTruth:
    """Read the ``gt/`` of a directory written by :func:`write_synth_input` (or ``gt/`` itself)."""
    directory = Path(directory)
    gt = directory / "gt" if (directory / "gt").is_dir() else directory
    files = ("primitives.json", "motion.npz", "meta.json", "cameras.npz", "contacts.npz")
    missing = [f for f in files if not (gt / f).is_file()]
    if missing:
        raise FileNotFoundError(f"{gt} is not a synthetic ground truth: missing {missing} (expected {list(files)})")
    with np.load(gt / "cameras.npz") as cams, np.load(gt / "contacts.npz") as contacts:
        return SynthTruth(boxes=load_primitives(gt / "primitives.json"), motion=Motion.load(gt / "motion.npz"),
                          cam_c2w=cams["cam_c2w"], world_from_input=cams["world_from_input"],
                          scale=float(cams["scale"]), contacts={k: contacts[k] for k in contacts.files},
                          meta=json.loads((gt / "meta.json").read_text()))


def alignment_errors(scale: float, world_from_input: np.ndarray, truth: SynthTruth | SynthVideo) -> dict[str, float]:
    """How far an estimated alignment (metric = ``scale`` × input, then the rigid
    ``world_from_input``) is from the truth.

    ``scale_error`` is relative; ``gravity_error_deg`` is the angle between the estimated and
    the true up direction; ``floor_error_m`` / ``floor_error_max_m`` are the mean / largest
    height, in the estimated world, of the true floor under the person's pelvis path (0 when the
    estimated floor is the true one there).
    """
    aligned_from_true = np.asarray(world_from_input) @ np.diag([*(np.full(3, scale / truth.scale)), 1.0]) \
        @ np.linalg.inv(truth.world_from_input)
    true_up = aligned_from_true[:3, :3] @ [0.0, 0.0, 1.0]
    gravity = np.degrees(np.arccos(np.clip(true_up[2] / np.linalg.norm(true_up), -1.0, 1.0)))
    floor = np.c_[truth.motion.root_pos[:, :2], np.zeros(truth.motion.num_frames)]
    heights = np.abs(floor @ aligned_from_true[:3, :3].T + aligned_from_true[:3, 3])[:, 2]
    return {"scale_error": float(scale / truth.scale - 1.0), "gravity_error_deg": float(gravity),
            "floor_error_m": float(heights.mean()), "floor_error_max_m": float(heights.max())}
