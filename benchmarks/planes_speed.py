"""Planar fitting speed and face recovery against Open3D's ``detect_planar_patches``, same run.

    python benchmarks/planes_speed.py --index 0     # 300 frames, 512x384, the suite's first video

The input is a video of the synthetic benchmark suite (:func:`crisp_gym.synth.video.benchmark_suite`:
stairs up, a platform, a seat, stairs down in turn, with background boxes, a moving handheld
camera, monocular-like depth noise), rendered with 300 frames at 512x384 and brought to metres
and the true world frame with its ground truth, person pixels removed, so that only planar
fitting is measured (alignment is not).

* **ours**: :func:`crisp_gym.reconstruct.planes.fit_planes` end to end on all frames, with the pelvis path;
  per-frame time = total / frames.
* **Open3D**: per frame, ``estimate_normals`` (30 nearest neighbours; the patch detector needs
  normals) + ``detect_planar_patches`` (its documented defaults), on the frame's points after the
  same depth-percentile and pelvis filters ours applies: at full resolution on every
  ``--o3d-every``-th frame, and on every frame subsampled to ours' grid resolution (every 4th pixel
  both ways, about as many points as ours fits normals on).

A true planar face is the exposed part of a face of a ground-truth box (the floor slab left out:
it is 40 m wide) that the filtered points cover at least half of. It is recovered when some
fitted rectangle (ours: each box's +z face; Open3D: each patch) lies on its plane (normals within
18°, offset within 5 cm) with IoU >= 0.5 on that plane; the same matching for both.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, replace

import numpy as np
import open3d as o3d
from matplotlib.path import Path as PolygonPath
from scipy.spatial import cKDTree
from tqdm import tqdm

from crisp_gym.metrics import box_signed_distance
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.planes import PlaneFitConfig, fit_planes
from crisp_gym.scene import Box
from crisp_gym.synth.video import SynthVideoConfig, benchmark_suite, render_synth_video

PLANE_COSINE = np.cos(np.radians(18.0))
PLANE_OFFSET = 0.05
MIN_IOU = 0.5
FACE_CELL = 0.01
O3D_KNN = 30


@dataclass(frozen=True)
class Rectangle:
    """A planar rectangle: centre (3,), unit axes u, v (3,), half extents (2,)."""

    centre: np.ndarray
    u: np.ndarray
    v: np.ndarray
    half: np.ndarray

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)

    def corners(self) -> np.ndarray:
        signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float) * self.half
        return self.centre + signs[:, :1] * self.u + signs[:, 1:] * self.v


@dataclass(frozen=True)
class Face:
    """The exposed part of a ground-truth box face: its rectangle and the exposed cell centres."""

    name: str
    rect: Rectangle
    cells: np.ndarray  # (N, 2) exposed cell centres in (u, v) face coordinates

    @property
    def area(self) -> float:
        return len(self.cells) * FACE_CELL**2


def exposed_faces(boxes: list[Box]) -> list[Face]:
    """Faces of the non-floor boxes, reduced to the parts not buried in another box."""
    faces = []
    for i, box in enumerate(boxes):
        if box.name == "floor":
            continue
        others = boxes[:i] + boxes[i + 1:]
        for axis in range(3):
            a, b = [k for k in range(3) if k != axis]
            for sign in (-1.0, 1.0):
                normal = sign * box.rotation[:, axis]
                u = box.rotation[:, a]
                v = np.cross(normal, u)
                rect = Rectangle(box.center + box.half_size[axis] * normal, u, v, box.half_size[[a, b]])
                nu, nv = np.ceil(2 * rect.half / FACE_CELL).astype(int)
                gu, gv = np.meshgrid((np.arange(nu) + 0.5) / nu * 2 - 1, (np.arange(nv) + 0.5) / nv * 2 - 1,
                                     indexing="ij")
                uv = np.stack([gu.ravel() * rect.half[0], gv.ravel() * rect.half[1]], axis=1)
                points = rect.centre + uv[:, :1] * u + uv[:, 1:] * v + 0.002 * normal
                exposed = box_signed_distance(points, others) > 0
                if exposed.sum() * FACE_CELL**2 >= 0.01:
                    faces.append(Face(f"{box.name or i}{'+-'[sign < 0]}{'xyz'[axis]}", rect, uv[exposed]))
    return faces


def observed_fraction(face: Face, points: np.ndarray, cameras: np.ndarray, cell: float = 0.05) -> float:
    """Share of the face's exposed area (on a ``cell`` grid) that ``points`` lie on (within 2 cm of
    its plane and 3 cm inside its edges, so the neighbouring faces' points do not count); 0 when
    the face turns its back on every camera (drifting depth can put a front face's points there)."""
    if not np.any((cameras - face.rect.centre) @ face.rect.normal > 0):
        return 0.0
    rel = points - face.rect.centre
    near = np.abs(rel @ face.rect.normal) < 0.02
    uv = np.stack([rel[near] @ face.rect.u, rel[near] @ face.rect.v], axis=1)
    inside = np.all(np.abs(uv) <= face.rect.half - 0.03, axis=1)
    seen = {tuple(c) for c in np.floor(uv[inside] / cell).astype(int)}
    cells = {tuple(c) for c in np.floor(face.cells / cell).astype(int)}
    return len(seen & cells) / max(len(cells), 1)


def face_iou(face: Face, rect: Rectangle) -> float:
    """IoU on the face's plane of the exposed face and ``rect`` (0 if ``rect`` is not on the plane)."""
    if abs(face.rect.normal @ rect.normal) < PLANE_COSINE or \
            abs(face.rect.normal @ (rect.centre - face.rect.centre)) > PLANE_OFFSET:
        return 0.0
    rel = rect.corners() - face.rect.centre
    polygon = np.stack([rel @ face.rect.u, rel @ face.rect.v], axis=1)
    x, y = polygon[:, 0], polygon[:, 1]
    area = 0.5 * abs(x @ np.roll(y, 1) - y @ np.roll(x, 1))
    inter = PolygonPath(polygon).contains_points(face.cells).sum() * FACE_CELL**2
    return float(inter / (face.area + area - inter))


def recovered(faces: list[Face], rects: list[Rectangle]) -> int:
    """Number of faces some rectangle matches with IoU >= 0.5."""
    return sum(any(face_iou(face, r) >= MIN_IOU for r in rects) for face in faces)


def box_rectangles(boxes: list[Box]) -> list[Rectangle]:
    """Each fitted box's +z face: the surface it was fitted to."""
    return [Rectangle(b.center + b.half_size[2] * b.rotation[:, 2], b.rotation[:, 0], b.rotation[:, 1],
                      b.half_size[:2]) for b in boxes]


def filtered_points(frames: Frames, t: int, pelvis: cKDTree, cfg: PlaneFitConfig, step: int = 1) -> np.ndarray:
    """Frame ``t``'s world points (every ``step``-th pixel) after ours' depth-percentile and pelvis filters."""
    depth = frames.depth[t]
    valid = depth > 0
    valid &= depth <= np.percentile(depth[valid], cfg.depth_percentile)
    points = frames.world_points(t)[::step, ::step][valid[::step, ::step]]
    distance, _ = pelvis.query(points, distance_upper_bound=cfg.pelvis_radius)
    return points[np.isfinite(distance)]


def open3d_patches(points: np.ndarray) -> tuple[list[Rectangle], float]:
    """Open3D's planar patches of one frame's points, and the seconds (normals + patches) it took."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    start = time.perf_counter()
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(O3D_KNN))
    patches = cloud.detect_planar_patches(search_param=o3d.geometry.KDTreeSearchParamKNN(O3D_KNN))
    seconds = time.perf_counter() - start
    rects = []
    for patch in patches:
        rotation, extent = np.asarray(patch.R), np.asarray(patch.extent)
        k = int(np.argmin(extent))
        a, b = [i for i in range(3) if i != k]
        rects.append(Rectangle(np.asarray(patch.center), rotation[:, a], rotation[:, b], extent[[a, b]] / 2))
    return rects, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--index", type=int, default=0, help="which video of the benchmark suite (0-9)")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--o3d-every", type=int, default=10, help="run full-resolution Open3D on every n-th frame")
    args = parser.parse_args()

    suite = benchmark_suite()
    if not 0 <= args.index < len(suite):
        parser.error(f"--index must be in 0..{len(suite) - 1}")
    spec = suite[args.index]
    video = render_synth_video(spec, SynthVideoConfig(frames=args.frames), progress=False)
    frames = video.frames.scaled(video.scale).transformed(video.world_from_input)
    frames = replace(frames, depth=np.where(frames.person_mask, 0.0, frames.depth).astype(np.float32))
    pelvis = video.motion.root_pos
    pelvis_tree = cKDTree(pelvis)
    cfg = PlaneFitConfig()

    start = time.perf_counter()
    fit = fit_planes(frames, pelvis_path=pelvis, cfg=cfg, progress=False)
    ours_total = time.perf_counter() - start

    full_rects, full_seconds, grid_rects, grid_seconds, seen = [], [], [], [], []
    for t in tqdm(range(frames.num_frames), desc="open3d", unit="frame"):
        rects, seconds = open3d_patches(filtered_points(frames, t, pelvis_tree, cfg, step=4))
        grid_rects += rects
        grid_seconds.append(seconds)
        if t % args.o3d_every == 0:
            points = filtered_points(frames, t, pelvis_tree, cfg)
            seen.append(points)
            rects, seconds = open3d_patches(points)
            full_rects += rects
            full_seconds.append(seconds)

    seen_points = np.concatenate(seen)
    cameras = frames.cam_c2w[:, :3, 3]
    faces = [f for f in exposed_faces(video.boxes) if observed_fraction(f, seen_points, cameras) >= 0.5]
    ours_frame = ours_total / frames.num_frames
    rows = [
        ("ours: fit_planes, all frames", ours_frame, ours_total, len(fit.boxes), recovered(faces, box_rectangles(fit.boxes))),
        (f"Open3D, full resolution, every {args.o3d_every}th frame", np.mean(full_seconds), None, len(full_rects),
         recovered(faces, full_rects)),
        ("Open3D, every 4th pixel, all frames", np.mean(grid_seconds), float(np.sum(grid_seconds)), len(grid_rects),
         recovered(faces, grid_rects)),
    ]
    h, w = frames.image_size
    print(f"\n{spec.name}: {frames.num_frames} frames, {w}x{h}; {len(faces)} true planar faces in view; "
          f"stages (s): " + ", ".join(f"{k} {v:.1f}" for k, v in fit.timings.items()))
    print("| method | per frame (ms) | Open3D / ours per frame | total (s) | rectangles | faces recovered |")
    print("|---|---|---|---|---|---|")
    for name, per_frame, total, count, found in rows:
        print(f"| {name} | {1000 * per_frame:.0f} | {per_frame / ours_frame:.1f}x | "
              f"{'-' if total is None else f'{total:.1f}'} | {count} | {found} / {len(faces)} |")


if __name__ == "__main__":
    main()
