"""A cache of the plain-video path's two slow stages: the person track (MediaPipe) and the camera solve (COLMAP).

They are over 90 % of a run's time (about 3 minutes for 8.5 s of phone video on 2 cores), and
neither depends on the settings that come after them (the person's stature, the floor, seats,
contacts), so a re-run with other such settings reuses them. COLMAP's multithreaded mapping is
not bit-reproducible either: a cached solve is also how two settings are compared on the same one.

Each entry is an npz named by a digest of what it was computed from: the frames' pixels and, for
the cameras, the :class:`~reconstruct.sfm.SfmConfig` and whether structure from motion was asked
for. A changed video or setting misses the cache; nothing is ever overwritten in place (a new
entry is written to a temporary file and renamed).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from crisp_gym.atomic import atomic_path
from crisp_gym.reconstruct.person import MEDIAPIPE_VERSION, PersonTrack
from crisp_gym.reconstruct.sfm import CameraSolve

T = TypeVar("T")


def frames_digest(frames: np.ndarray) -> str:
    """A digest of the frames' shape and pixels."""
    digest = hashlib.sha256(repr(frames.shape).encode())
    digest.update(np.ascontiguousarray(frames).data)
    return digest.hexdigest()[:24]


def _entry(cache: Path, kind: str, *parts: str) -> Path:
    key = hashlib.sha256("\n".join(parts).encode()).hexdigest()[:24]
    return cache / f"{kind}-{key}.npz"


def _write(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, **arrays)


def track_to_arrays(track: PersonTrack) -> dict[str, np.ndarray]:
    return {"image": track.image, "world": track.world, "visibility": track.visibility,
            "masks": np.packbits(track.masks, axis=-1), "mask_width": np.array(track.masks.shape[-1])}


def track_from_arrays(data) -> PersonTrack:
    masks = np.unpackbits(data["masks"], axis=-1, count=int(data["mask_width"])).astype(bool)
    return PersonTrack(image=data["image"], world=data["world"], visibility=data["visibility"], masks=masks)


def cameras_to_arrays(cameras: CameraSolve) -> dict[str, np.ndarray]:
    counts = np.array([len(v) for v in cameras.visible], dtype=np.int64)
    return {"intrinsic": cameras.intrinsic, "cam_c2w": cameras.cam_c2w, "keyframes": cameras.keyframes,
            "registered": cameras.registered, "points": cameras.points, "colors": cameras.colors,
            "visible": np.concatenate([*cameras.visible, np.zeros(0, np.int64)]).astype(np.int64),
            "visible_counts": counts, "reprojection_error": np.array(cameras.reprojection_error),
            "static": np.array(cameras.static), "reason": np.array(cameras.reason),
            "seconds_names": np.array(list(cameras.seconds), dtype=str),
            "seconds": np.array(list(cameras.seconds.values()), dtype=float)}


def cameras_from_arrays(data) -> CameraSolve:
    visible = np.split(data["visible"], np.cumsum(data["visible_counts"])[:-1]) if len(data["visible_counts"]) else []
    return CameraSolve(intrinsic=data["intrinsic"], cam_c2w=data["cam_c2w"], keyframes=data["keyframes"],
                       registered=data["registered"], points=data["points"], colors=data["colors"], visible=visible,
                       reprojection_error=float(data["reprojection_error"]), static=bool(data["static"]),
                       reason=str(data["reason"]),
                       seconds=dict(zip(data["seconds_names"].tolist(), data["seconds"].tolist(), strict=True)))


def _cached(cache: Path | None, kind: str, digest: str, key: str, compute: Callable[[], T],
            to_arrays: Callable[[T], dict[str, np.ndarray]], from_arrays: Callable[..., T]) -> tuple[T, bool]:
    """``compute()``'s result for the frames with ``digest`` under ``key``: from ``cache`` when
    there, else computed (and stored when ``cache`` is given); and whether it came from the cache."""
    if cache is None:
        return compute(), False
    path = _entry(Path(cache), kind, digest, key)
    if path.is_file():
        with np.load(path) as data:
            return from_arrays(data), True
    result = compute()
    _write(path, to_arrays(result))
    return result, False


def cached_track(cache: Path | None, digest: str, compute: Callable[[], PersonTrack]) -> tuple[PersonTrack, bool]:
    """The person track of the frames with ``digest``: from ``cache`` when there, else computed
    (and stored when ``cache`` is given); and whether it came from the cache."""
    return _cached(cache, "person", digest, MEDIAPIPE_VERSION, compute, track_to_arrays, track_from_arrays)


def cached_cameras(cache: Path | None, digest: str, settings: str,
                   compute: Callable[[], CameraSolve]) -> tuple[CameraSolve, bool]:
    """The camera solve of the frames with ``digest`` under ``settings`` (a text naming every
    setting it depends on), as :func:`cached_track` does it."""
    return _cached(cache, "cameras", digest, settings, compute, cameras_to_arrays, cameras_from_arrays)
