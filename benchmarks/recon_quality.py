"""Reconstruction quality on the synthetic benchmark suite, against TSDF baselines in the same run.

    python benchmarks/recon_quality.py --seeds 10 --out results/recon_quality
    python benchmarks/recon_quality.py --contact-ablation --seeds 6 --out results/contact_ablation

Each case renders a synthetic video (noisy monocular-like depth, unknown scale and gravity, a
moving camera; :mod:`crisp_gym.synth.video`), writes it as ``crisp reconstruct`` input, reads it
back and runs the pipeline. The reconstruction is compared with the ground truth after the only
transform the pipeline is free to choose: the world's heading and horizontal origin, fitted on the
human's pelvis path (scale, gravity and floor height errors stay in the numbers).

Default mode (issue "Reconstruction"): median one-way Chamfer Recon→GT and GT→Recon, coverage
of GT support surfaces (3 cm), primitive count and non-penetration for the planar primitives,
and the same geometry metrics for the TSDF mesh fused from the same aligned depth.

``--contact-ablation`` (paper Table 3): the occluded-support suite (a seat hidden below the
camera's view, a platform off-frame) without and with contact completion: Chamfer both ways,
non-penetration, and per hidden support whether it is missing without completion, the contact
primitive's height error and its coverage of the true contact footprint; contact primitives
where the truth has no support count as false.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from crisp_gym.metrics import support_tops
from crisp_gym.reconstruct.baselines import TsdfConfig, tsdf_mesh
from crisp_gym.reconstruct.io import read_frames, read_motion
from crisp_gym.reconstruct.metrics import (
    chamfer_gt_to_recon,
    chamfer_recon_to_gt,
    heading_alignment,
    non_penetration,
    primitive_count,
    support_coverage,
)
from crisp_gym.reconstruct.pipeline import Reconstruction, reconstruct
from crisp_gym.scene import Box
from crisp_gym.synth.truth import load_ground_truth, write_synth_input
from crisp_gym.synth.video import SynthSpec, SynthVideoConfig, benchmark_suite, occluded_suite, render_synth_video

ROI_MARGIN = 2.5  # m around the pelvis path: the pipeline's own filter radius (precision)
SUPPORT_MARGIN = 1.0  # m around the pelvis path: the surfaces a person there could use (completeness)
SUPPORT_TOLERANCE = 0.05  # m: the contact-completion criterion's height tolerance
FOOTPRINT_GRID = 0.01  # m: grid spacing for footprint coverage


def _prepare(spec: SynthSpec, size: tuple[int, int], workdir: Path) -> Path:
    video = render_synth_video(spec, SynthVideoConfig(width=size[0], height=size[1]), progress=False)
    return write_synth_input(workdir / spec.name, video, overwrite=True)


def _run(source: Path, contacts: str) -> Reconstruction:
    frames = read_frames(source / "input.npz", progress=False)
    motion = read_motion(source / "motion_camera.npz", frame="camera")
    return reconstruct(frames, motion, contacts=contacts, progress=False)


def _roi(gt_motion_root: np.ndarray, margin: float) -> np.ndarray:
    lo = gt_motion_root.min(0) - margin
    hi = gt_motion_root.max(0) + margin
    return np.array([[lo[0], lo[1], -0.5], [hi[0], hi[1], 3.0]])


def _geometry_row(recon, gt: list[Box], path: np.ndarray) -> dict:
    """Precision within the pipeline's radius of the path; completeness and coverage over the
    surfaces near enough to the path to be used (the camera never saw most of a 40 m floor)."""
    if isinstance(recon, list) and not recon:
        return {"chamfer_recon_to_gt_cm": float("nan"), "chamfer_gt_to_recon_cm": float("inf"),
                "chamfer_recon_to_gt_mean_cm": float("nan"), "chamfer_gt_to_recon_mean_cm": float("inf"),
                "coverage": 0.0, "primitives": 0}
    forward = chamfer_recon_to_gt(recon, gt, bounds=_roi(path, ROI_MARGIN))
    near = _roi(path, SUPPORT_MARGIN)
    backward = chamfer_gt_to_recon(recon, gt, bounds=near)
    return {"chamfer_recon_to_gt_cm": 100 * forward.median, "chamfer_gt_to_recon_cm": 100 * backward.median,
            "chamfer_recon_to_gt_mean_cm": 100 * forward.mean, "chamfer_gt_to_recon_mean_cm": 100 * backward.mean,
            "coverage": support_coverage(recon, gt, bounds=near), "primitives": primitive_count(recon)}


def quality_case(spec: SynthSpec, size: tuple[int, int], workdir: Path, baselines: bool) -> dict:
    """Planar primitives (+ contact completion) vs ground truth, and the TSDF mesh of the same depth."""
    source = _prepare(spec, size, workdir)
    truth = load_ground_truth(source)
    start = time.perf_counter()
    result = _run(source, "kinematic")
    seconds = time.perf_counter() - start
    to_gt = heading_alignment(result.motion.root_pos, truth.motion.root_pos)
    boxes = [b.transformed(to_gt) for b in result.boxes]
    row = {"case": spec.name, "seconds": seconds, "scale_error": result.alignment.scale / truth.scale - 1.0,
           **_geometry_row(boxes, truth.boxes, truth.motion.root_pos),
           "non_penetration": non_penetration(result.boxes, result.motion).vertex_score,
           "gt_non_penetration": non_penetration(truth.boxes, truth.motion).vertex_score,
           "contact_primitives": sum(b.source == "contact" for b in result.boxes)}
    if baselines:
        start = time.perf_counter()
        mesh = tsdf_mesh(result.frames, TsdfConfig(), progress=False).apply_transform(to_gt)
        tsdf = _geometry_row(mesh, truth.boxes, truth.motion.root_pos)
        row |= {f"tsdf_{k}": v for k, v in tsdf.items()} | {"tsdf_seconds": time.perf_counter() - start}
    return row


def _footprint_points(truth, box: Box) -> np.ndarray:
    """(N, 2) grid points of the true contact footprint on ``box``: the convex hull of the
    ground-truth contact points that rest on its top."""
    from scipy.spatial import ConvexHull, Delaunay, QhullError

    points = truth.contacts["point"]
    top = box.top_height()
    on = np.abs(points[:, 2] - top) < SUPPORT_TOLERANCE
    on &= ~np.isnan(support_tops(points[:, :2], [box])[:, 0])
    xy = points[on, :2]
    if len(xy) < 3:
        return xy
    try:
        hull = ConvexHull(xy)
    except QhullError:
        return xy
    lo, hi = xy.min(0), xy.max(0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + FOOTPRINT_GRID, FOOTPRINT_GRID),
                         np.arange(lo[1], hi[1] + FOOTPRINT_GRID, FOOTPRINT_GRID))
    grid = np.c_[gx.ravel(), gy.ravel()]
    return grid[Delaunay(xy[hull.vertices]).find_simplex(grid) >= 0]


def _supported_fraction(xy: np.ndarray, height: float, boxes: list[Box]) -> float:
    """Fraction of the points ``xy`` with a surface of ``boxes`` within the tolerance of ``height``."""
    if not boxes or len(xy) == 0:
        return 0.0
    tops = support_tops(xy, boxes)
    return float(np.mean(np.any(np.abs(tops - height) <= SUPPORT_TOLERANCE, axis=1)))


def ablation_case(spec: SynthSpec, size: tuple[int, int], workdir: Path) -> dict:
    """One occluded-support case without and with contact completion."""
    source = _prepare(spec, size, workdir)
    truth = load_ground_truth(source)
    visible = {b["name"]: b["top_visible_pixels"] for b in truth.meta["boxes"]}
    hidden_ids = [i for i, box in enumerate(truth.boxes) if visible.get(box.name, 1) == 0 and box.top_height() > 0.05]
    row: dict = {"case": spec.name, "hidden": [truth.boxes[i].name for i in hidden_ids]}
    for mode in ("none", "kinematic"):
        result = _run(source, mode)
        to_gt = heading_alignment(result.motion.root_pos, truth.motion.root_pos)
        boxes = [b.transformed(to_gt) for b in result.boxes]
        geometry = _geometry_row(boxes, truth.boxes, truth.motion.root_pos)
        # an empty scene has nothing to penetrate: the missing support shows in coverage instead
        score = non_penetration(result.boxes, result.motion).vertex_score if result.boxes else 1.0
        row[mode] = {**geometry, "non_penetration": score}
        contact = [b for b in boxes if b.source == "contact"]
        supports = []
        for i in hidden_ids:
            box = truth.boxes[i]
            footprint = _footprint_points(truth, box)
            if len(footprint) == 0:  # hidden but never touched (a backrest nobody leaned on)
                continue
            errors = [abs(b.top_height() - box.top_height()) for b in contact
                      if _supported_fraction(footprint, b.top_height(), [b]) > 0]
            supports.append({"name": box.name, "footprint_points": len(footprint),
                             "supported_fraction": _supported_fraction(footprint, box.top_height(), boxes),
                             "contact_coverage": _supported_fraction(footprint, box.top_height(), contact),
                             "contact_height_error_cm": 100 * min(errors) if errors else None})
        # a contact primitive is false when no true surface lies within the tolerance of its top
        false = 0
        for b in contact:
            centre_top = b.center + b.half_size[2] * b.rotation[:, 2]
            tops = support_tops(centre_top[None, :2], truth.boxes)[0]
            false += not np.any(np.abs(tops - centre_top[2]) <= SUPPORT_TOLERANCE)
        row[mode] |= {"supports": supports, "contact_primitives": len(contact), "false_contact_primitives": false}
    return row


def _median(rows: list[dict], key: str) -> float:
    return float(np.median([r[key] for r in rows]))


def quality_table(rows: list[dict]) -> str:
    keys = [("chamfer_recon_to_gt_cm", "Chamfer Recon→GT (cm, median)"),
            ("chamfer_gt_to_recon_cm", "Chamfer GT→Recon (cm, median)"), ("coverage", "support coverage (3 cm)"),
            ("primitives", "primitives / triangles")]
    lines = ["| metric | planar primitives | TSDF mesh |", "|---|---|---|"]
    for key, label in keys:
        tsdf = f"{_median(rows, 'tsdf_' + key):.3g}" if f"tsdf_{key}" in rows[0] else "—"
        lines.append(f"| {label} | {_median(rows, key):.3g} | {tsdf} |")
    lines.append(f"| non-penetration (reconstructed motion in its scene) | {_median(rows, 'non_penetration'):.3f} | — |")
    lines.append(f"| max primitives over cases | {max(r['primitives'] for r in rows)} | — |")
    lines.append(f"| median seconds per case (pipeline) | {_median(rows, 'seconds'):.1f} | "
                 + (f"{_median(rows, 'tsdf_seconds'):.1f} |" if "tsdf_seconds" in rows[0] else "— |"))
    return "\n".join(lines)


def ablation_table(rows: list[dict]) -> str:
    lines = ["| | Chamfer Recon→GT (cm) | Chamfer GT→Recon (cm) | non-penetration | hidden supports found "
             "| contact top error (cm, max) | contact footprint coverage (min) | false contact primitives |",
             "|---|---|---|---|---|---|---|---|"]
    for mode, label in (("none", "without contact"), ("kinematic", "with contact")):
        cases = [r[mode] for r in rows]
        supports = [s for c in cases for s in c["supports"]]
        found = sum(s["supported_fraction"] >= 0.8 for s in supports)
        errors = [s["contact_height_error_cm"] for s in supports if s["contact_height_error_cm"] is not None]
        coverage = [s["contact_coverage"] for s in supports]
        cells = [label, f"{np.median([c['chamfer_recon_to_gt_cm'] for c in cases]):.2f}",
                 f"{np.median([c['chamfer_gt_to_recon_cm'] for c in cases]):.2f}",
                 f"{np.median([c['non_penetration'] for c in cases]):.3f}", f"{found}/{len(supports)}",
                 f"{max(errors):.1f}" if errors else "—", f"{min(coverage):.2f}" if coverage else "—",
                 str(sum(c["false_contact_primitives"] for c in cases))]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=10, help="number of cases (seeds 0..N-1)")
    parser.add_argument("--size", default="512x384", help="image size WIDTHxHEIGHT")
    parser.add_argument("--contact-ablation", action="store_true", help="run the occluded-support ablation")
    parser.add_argument("--no-baselines", action="store_true", help="skip the TSDF baseline")
    parser.add_argument("--out", type=Path, default=None, help="directory for results.json (and the inputs)")
    args = parser.parse_args()
    size = tuple(int(x) for x in args.size.lower().split("x"))
    out = args.out or Path(tempfile.mkdtemp(prefix="recon_quality_"))
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    if args.contact_ablation:
        for spec in tqdm(occluded_suite(range(args.seeds)), desc="ablation", unit="case"):
            rows.append(ablation_case(spec, size, out / "inputs"))
        table = ablation_table(rows)
    else:
        for spec in tqdm(benchmark_suite(range(args.seeds)), desc="quality", unit="case"):
            rows.append(quality_case(spec, size, out / "inputs", baselines=not args.no_baselines))
        table = quality_table(rows)
    (out / "results.json").write_text(json.dumps(rows, indent=2, default=float))
    print(table)
    print(f"\nper-case results: {out / 'results.json'}")


if __name__ == "__main__":
    main()
