"""``Frames``: the depth video every reconstruction stage reads.

One type for every input (a MegaSAM-style npz, an RGB-D folder, a synthetic render), so the
stages after reading never care where the frames came from.

==============  ==============  ====================================================================
field           shape / type    meaning
==============  ==============  ====================================================================
``depth``       (T, H, W) f32   z-depth along the camera's optical axis; 0 or NaN = no measurement;
                                metric only once ``scale`` has been applied (see ``align``)
``intrinsic``   (3, 3) f64      pinhole K (fx, fy, cx, cy), OpenCV convention
``cam_c2w``     (T, 4, 4) f64   camera → world, OpenCV camera axes (x right, y down, z forward)
``fps``         float           frame rate of the video
``rgb``         (T, H, W, 3) u8 optional colour
``person_mask`` (T, H, W) bool  optional, True where the person is
==============  ==============  ====================================================================
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from crisp_gym.geometry import pixel_rays


@dataclass(frozen=True)
class Frames:
    """A depth video with camera poses (see the module docstring for the fields)."""

    depth: np.ndarray
    intrinsic: np.ndarray
    cam_c2w: np.ndarray
    fps: float = 30.0
    rgb: np.ndarray | None = None
    person_mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        depth = np.asarray(self.depth)
        if depth.ndim != 3:
            raise ValueError(f"depth must be (T, H, W), got shape {depth.shape}")
        if depth.shape[0] == 0:
            raise ValueError("depth has zero frames; a reconstruction needs at least one")
        t, h, w = depth.shape
        k = np.asarray(self.intrinsic, dtype=np.float64)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ValueError(f"intrinsic must be a finite (3, 3) pinhole matrix with fx, fy > 0, got {k!r}")
        poses = np.asarray(self.cam_c2w, dtype=np.float64)
        if poses.shape != (t, 4, 4):
            raise ValueError(f"cam_c2w must be ({t}, 4, 4) to match depth, got {poses.shape}")
        if not np.all(np.isfinite(poses)):
            raise ValueError("cam_c2w contains NaN or infinite values")
        rot_err = np.abs(np.einsum("tij,tkj->tik", poses[:, :3, :3], poses[:, :3, :3]) - np.eye(3)).max()
        if rot_err > 1e-3:
            raise ValueError(f"cam_c2w rotations are not orthonormal (max |R Rᵀ - I| = {rot_err:.2e})")
        mirrored = np.flatnonzero(np.linalg.det(poses[:, :3, :3]) < 0)
        if mirrored.size:
            raise ValueError(f"cam_c2w rotations of {mirrored.size} frames (first: {mirrored[0]}) have determinant -1: "
                             "a mirror, not a camera pose (a flipped axis in the pose convention?)")
        bad_row = np.flatnonzero(np.abs(poses[:, 3] - (0.0, 0.0, 0.0, 1.0)).max(axis=1) > 1e-6)
        if bad_row.size:
            raise ValueError(f"cam_c2w bottom rows must be [0, 0, 0, 1]; {bad_row.size} frames (first: {bad_row[0]}) "
                             f"have {poses[bad_row[0], 3].tolist()} (transposed matrices?)")
        if not np.isfinite(self.fps) or self.fps <= 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        finite = np.isfinite(depth) & (depth > 0)
        if not finite.any():
            raise ValueError("depth has no valid (finite, positive) pixel in any frame")
        object.__setattr__(self, "depth", np.where(finite, depth, 0.0).astype(np.float32))
        object.__setattr__(self, "intrinsic", k)
        object.__setattr__(self, "cam_c2w", poses)
        if self.rgb is not None:
            rgb = np.asarray(self.rgb)
            if rgb.shape != (t, h, w, 3) or rgb.dtype != np.uint8:
                raise ValueError(f"rgb must be uint8 ({t}, {h}, {w}, 3), got {rgb.dtype} {rgb.shape}")
            object.__setattr__(self, "rgb", rgb)
        if self.person_mask is not None:
            mask = np.asarray(self.person_mask)
            if mask.shape != (t, h, w):
                raise ValueError(f"person_mask must be ({t}, {h}, {w}), got {mask.shape}")
            object.__setattr__(self, "person_mask", mask.astype(bool))

    @property
    def num_frames(self) -> int:
        return self.depth.shape[0]

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W)."""
        return self.depth.shape[1], self.depth.shape[2]

    @property
    def valid(self) -> np.ndarray:
        """(T, H, W) bool: pixels with a depth measurement."""
        return self.depth > 0

    def rays(self) -> np.ndarray:
        """(H, W, 3) camera-frame directions with unit z: a pixel's point is ``depth * ray``."""
        h, w = self.image_size
        return pixel_rays(self.intrinsic, w, h)

    def camera_points(self, t: int) -> np.ndarray:
        """(H, W, 3) frame ``t``'s pointmap in its camera frame (zeros where depth is missing)."""
        return self.depth[t, ..., None].astype(np.float64) * self.rays()

    def world_points(self, t: int) -> np.ndarray:
        """(H, W, 3) frame ``t``'s pointmap in the world frame (meaningless where depth is missing)."""
        pose = self.cam_c2w[t]
        return self.camera_points(t) @ pose[:3, :3].T + pose[:3, 3]

    def scaled(self, scale: float) -> Frames:
        """The same video with depth and camera translations multiplied by ``scale`` (e.g. to metres)."""
        if not np.isfinite(scale) or scale <= 0:
            raise ValueError(f"scale must be positive and finite, got {scale}")
        poses = self.cam_c2w.copy()
        poses[:, :3, 3] *= scale
        return replace(self, depth=self.depth * np.float32(scale), cam_c2w=poses)

    def transformed(self, world_from_old: np.ndarray) -> Frames:
        """The same video with camera poses re-expressed in a new world frame (rigid 4x4)."""
        m = np.asarray(world_from_old, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"world_from_old must be (4, 4), got {m.shape}")
        return replace(self, cam_c2w=np.einsum("ij,tjk->tik", m, self.cam_c2w))

    def subset(self, frames: np.ndarray | slice) -> Frames:
        """Only the selected frames."""
        return replace(
            self,
            depth=self.depth[frames],
            cam_c2w=self.cam_c2w[frames],
            rgb=None if self.rgb is None else self.rgb[frames],
            person_mask=None if self.person_mask is None else self.person_mask[frames],
        )
