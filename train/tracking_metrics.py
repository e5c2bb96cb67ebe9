"""Tracking metrics: pure functions over (T, J, 3) joint positions in metres (W-MPJPE, WA-MPJPE,
MPJPE, jitter, acceleration error; see :mod:`crisp_gym.train.evaluate` for their definitions)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

SEGMENT_FRAMES = 100


def _check_motion(name: str, x: np.ndarray, min_frames: int) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim != 3 or x.shape[-1] != 3 or x.shape[0] < min_frames:
        raise ValueError(f"{name} must be (T, J, 3) joint positions with T >= {min_frames}, got shape {x.shape}")
    return x


def rigid_align(source: np.ndarray, target: np.ndarray, fit: slice = slice(None)) -> np.ndarray:
    """``source`` (T, J, 3) moved by the rotation and translation that best map its frames
    ``fit`` onto those of ``target`` (least squares over all their joints; no scale)."""
    source, target = _check_motion("source", source, 1), _check_motion("target", target, 1)
    if source.shape != target.shape:
        raise ValueError(f"source and target must have the same shape, got {source.shape} and {target.shape}")
    a, b = source[fit].reshape(-1, 3), target[fit].reshape(-1, 3)
    if len(a) == 0:
        raise ValueError("the alignment frames are empty")
    a_mean, b_mean = a.mean(axis=0), b.mean(axis=0)
    rotation, _ = Rotation.align_vectors(b - b_mean, a - a_mean)
    return rotation.apply((source - a_mean).reshape(-1, 3)).reshape(source.shape) + b_mean


def segment_mpjpe(pred: np.ndarray, ref: np.ndarray, align: str = "segment",
                  segment: int = SEGMENT_FRAMES) -> float:
    """Mean per-joint position error (mm) over consecutive ``segment``-frame windows.

    Args:
        pred, ref: (T, J, 3) joint positions (m).
        align: ``"segment"`` (WA-MPJPE: each window rigidly aligned on all its frames),
            ``"first_two"`` (W-MPJPE: aligned on its first two frames) or ``"none"``.
        segment: window length; the last window holds the remaining frames.
    """
    pred, ref = _check_motion("pred", pred, 1), _check_motion("ref", ref, 1)
    if pred.shape != ref.shape:
        raise ValueError(f"pred and ref must have the same shape, got {pred.shape} and {ref.shape}")
    fits = {"segment": slice(None), "first_two": slice(0, 2), "none": None}
    if align not in fits:
        raise ValueError(f"align must be one of {sorted(fits)}, got {align!r}")
    if segment < 1:
        raise ValueError(f"segment must be at least 1 frame, got {segment}")
    errors = []
    for start in range(0, len(pred), segment):
        p, r = pred[start:start + segment], ref[start:start + segment]
        if fits[align] is not None:
            p = rigid_align(p, r, fits[align])
        errors.append(np.linalg.norm(p - r, axis=-1))
    return float(np.concatenate(errors).mean() * 1000.0)


def jitter(positions: np.ndarray, fps: float) -> float:
    """Mean norm of the joints' jerk (m/s³): third finite difference × fps³."""
    x = _check_motion("positions", positions, 4)
    jerk = np.diff(x, n=3, axis=0) * fps ** 3
    return float(np.linalg.norm(jerk, axis=-1).mean())


def accel_error(pred: np.ndarray, ref: np.ndarray) -> float:
    """Mean norm of the difference of the joints' accelerations (mm/frame²)."""
    pred, ref = _check_motion("pred", pred, 3), _check_motion("ref", ref, 3)
    if pred.shape != ref.shape:
        raise ValueError(f"pred and ref must have the same shape, got {pred.shape} and {ref.shape}")
    diff = np.diff(pred, n=2, axis=0) - np.diff(ref, n=2, axis=0)
    return float(np.linalg.norm(diff, axis=-1).mean() * 1000.0)
