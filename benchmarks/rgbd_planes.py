"""Planar fitting on a real RGB-D folder: how much of the planar surfaces the boxes cover.

    python benchmarks/rgbd_planes.py                              # ../shared/data/slambook2_rgbd
    python benchmarks/rgbd_planes.py --folder DIR --intrinsics FX FY CX CY --depth-scale S

The folder is reconstructed as ``crisp reconstruct DIR --metric --intrinsics ... --depth-scale ...``
does (same reader, alignment and planar fit), then measured in the scene's frame:

* **planar pixels**, chosen independently of the fit: per frame, Open3D's RANSAC
  (``PointCloud.segment_plane``, 2 cm, 1,000 iterations) is run repeatedly on the frame's points,
  each time removing the plane it finds, for up to ``--max-planes`` planes; a plane counts when its
  inliers are at least ``--min-plane-share`` of the frame's valid pixels and form one connected
  region in the image of at least that share (a surface, not a sheet of scattered points that
  happens to be coplanar). Their inliers are the planar pixels;
* **coverage**: the share of planar pixels within 5 cm of a box (unsigned distance to the union
  of boxes), per frame and over all frames (target ≥ 70 %);
* **unsupported boxes**: boxes farther than 5 cm from every observed point (target: none);
* for reference, the share of *all* valid pixels within 5 cm of a box (clutter, chairs and
  objects on the table included, which boxes are not meant to cover).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import tyro
from scipy.spatial import cKDTree

from crisp_gym.metrics import box_signed_distance
from crisp_gym.reconstruct.io import RgbdFolderConfig, read_frames
from crisp_gym.reconstruct.pipeline import reconstruct

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "slambook2_rgbd"


@dataclass(frozen=True)
class Args:
    folder: Path = SHARED
    """An RGB-D folder (TUM or Redwood layout)."""
    intrinsics: tuple[float, float, float, float] = (518.0, 519.0, 325.5, 253.5)
    """FX FY CX CY of the depth images (pixels)."""
    depth_scale: float = 1000.0
    """Depth image units per metre."""
    within: float = 0.05
    """m: a planar pixel is covered within this distance of a box; a box is supported within it of a point."""
    max_planes: int = 8
    """RANSAC planes sought per frame."""
    min_plane_share: float = 0.03
    """A plane counts when its largest connected region holds this share of the frame's valid pixels."""
    stride: int = 2
    """Every stride-th pixel in each direction is measured."""
    seed: int = 0
    json_out: Path | None = None
    """Also write the results here."""


def planar_pixels(points: np.ndarray, valid: np.ndarray, args: Args) -> np.ndarray:
    """(H, W) mask of the pixels on large planes of one frame (module docstring)."""
    h, w = valid.shape
    index = np.flatnonzero(valid.ravel())
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.reshape(-1, 3)[index]))
    remaining = np.arange(len(index))
    mask = np.zeros(h * w, dtype=bool)
    o3d.utility.random.seed(args.seed)
    for _ in range(args.max_planes):
        if len(remaining) < args.min_plane_share * len(index):
            break
        _, inliers = cloud.select_by_index(remaining).segment_plane(0.02, 3, 1000)
        inliers = remaining[np.asarray(inliers, dtype=int)]
        plane = np.zeros(h * w, dtype=np.uint8)
        plane[index[inliers]] = 1
        count, labels = cv2.connectedComponents(plane.reshape(h, w), connectivity=8)
        sizes = np.bincount(labels.ravel(), minlength=count)[1:]
        if sizes.size == 0 or sizes.max() < args.min_plane_share * len(index):
            break  # the best plane left is no large surface
        keep = labels.ravel() == 1 + int(np.argmax(sizes))
        mask |= keep
        remaining = np.setdiff1d(remaining, inliers)
    return mask.reshape(h, w)


def main(args: Args) -> dict:
    start = time.perf_counter()
    frames = read_frames(args.folder, progress=False,
                         rgbd=RgbdFolderConfig(intrinsics=args.intrinsics, depth_scale=args.depth_scale))
    result = reconstruct(frames, None, metric=True, progress=False)
    seconds = time.perf_counter() - start
    aligned = result.frames
    boxes = result.boxes
    rows, covered_all, planar_all, near_all, observed = [], 0, 0, 0, []
    for t in range(aligned.num_frames):
        points = aligned.world_points(t)[:: args.stride, :: args.stride]
        valid = aligned.valid[t][:: args.stride, :: args.stride]
        mask = planar_pixels(points, valid, args)
        distance = np.abs(box_signed_distance(points[mask], boxes))
        covered = int((distance <= args.within).sum())
        rows.append({"frame": t, "valid_pixels": int(valid.sum()), "planar_pixels": int(mask.sum()),
                     "covered": round(covered / max(int(mask.sum()), 1), 3)})
        covered_all += covered
        planar_all += int(mask.sum())
        near_all += int((np.abs(box_signed_distance(points[valid], boxes)) <= args.within).sum())
        observed.append(points[valid])
    tree = cKDTree(np.concatenate(observed))
    unsupported = []
    for box in boxes:  # nearest observed point to the box: sample its surface densely enough
        grid = np.stack(np.meshgrid(*[np.linspace(-1, 1, 9)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
        on_surface = grid[np.abs(grid).max(axis=1) == 1] * box.half_size @ box.rotation.T + box.center
        gap = float(tree.query(on_surface)[0].min())
        if gap > args.within:
            unsupported.append({"box": box.name, "gap_m": round(gap, 3)})
    out = {"folder": str(args.folder), "boxes": len(boxes), "seconds": round(seconds, 2),
           "coverage": round(covered_all / max(planar_all, 1), 3),
           "valid_pixels_near_a_box": round(near_all / max(sum(r["valid_pixels"] for r in rows), 1), 3),
           "frames": rows, "unsupported_boxes": unsupported}
    per_frame = ", ".join(f"{r['covered']:.0%}" for r in rows)
    print(f"{args.folder.name}: {len(boxes)} boxes in {seconds:.1f} s; planar pixels within {args.within * 100:.0f} cm "
          f"of a box: {out['coverage']:.1%} (per frame {per_frame}); "
          f"boxes farther than {args.within * 100:.0f} cm from every observed point: {len(unsupported)}; all valid "
          f"pixels within {args.within * 100:.0f} cm of a box: {out['valid_pixels_near_a_box']:.1%}")
    if args.json_out is not None:
        args.json_out.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main(tyro.cli(Args))
