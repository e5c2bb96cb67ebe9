"""Motion import over real files: time, up axis, grounding of the planted feet, skating, balance.

Every motion file of a folder (default: the SMPL motions estimated from real videos in
``../shared/data/asap_video_smpl``) is read as ``crisp import-motion`` reads it
(:func:`crisp_gym.import_motion.read_motion`), once grounded frame by frame from the planted feet
(the default) and once by one constant offset (the former behaviour), and a Markdown table is
printed. Planted feet are those of :func:`crisp_gym.motion.planted_feet`; a foot's height is the
lower of its ankle's and toe's sole points, and a frame's planted-foot height is that of its lowest
planted foot. Target: median planted-foot height within 1 cm of the floor for every file. Balance is
what the import reports (:func:`crisp_gym.balance.followability`): the shares of frames whose centre
of pressure lies over 10 cm outside the feet on the floor, and with no foot down under load. Every
planted foot, not only the lowest: the shares more than 1 and 2 cm above the floor, with the legs
bent to plant them (``plant_feet=True``, ``--plant-feet``) and as read (the default); the balance
shares for both. Joint ranges: the share of hinge values the import fitted into the humanoid's
ranges (BVH, ``ReadMotion.range_fit``) and the share it left outside them, for the simulator's
joint limits to clip (the SMPL family, read as decomposed).

    python benchmarks/motion_import.py [FOLDER]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from crisp_gym.balance import followability
from crisp_gym.humanoid import build_humanoid, hinge_ranges
from crisp_gym.import_motion import MOTION_SUFFIXES, read_motion
from crisp_gym.metrics import foot_heights, foot_skating, sole_points
from crisp_gym.motion import Motion, planted_feet, side_sole_heights

DEFAULT_FOLDER = Path(__file__).resolve().parents[2] / "shared" / "data" / "asap_video_smpl"


def planted_foot_heights(motion: Motion, model) -> tuple[np.ndarray, float]:
    """Per frame with a planted foot, the height (m) of the lowest planted foot (the lower of its
    ankle's and toe's soles; a raised foot held still counts as planted, the standing one is
    lower), and the mean horizontal speed (m/s) of the planted feet's soles."""
    planted = planted_feet(motion, model)  # (T, 2): left, right
    soles = sole_points(model, motion.qpos())  # (T, 4, 3): L ankle, L toe, R ankle, R toe
    height = np.where(planted, foot_heights(soles), np.inf).min(axis=1)
    skating = foot_skating(soles, np.repeat(planted, 2, axis=1), motion.fps)
    return height[np.isfinite(height)], skating.mean_speed


def floating_share(motion: Motion, model, above: float) -> float:
    """The share of planted feet (each foot in each frame it is planted) whose lowest point (of its
    collision geoms, what meets the floor in simulation) is more than ``above`` metres over the
    floor: mostly the other foot of a frame grounded on its lower one."""
    planted = planted_feet(motion, model)
    if not planted.any():
        return 0.0
    return float(np.mean(side_sole_heights(motion, model)[planted] > above))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, nargs="?", default=DEFAULT_FOLDER)
    args = parser.parse_args(argv)
    files = sorted(f for f in args.folder.iterdir() if f.suffix.lower() in MOTION_SUFFIXES)
    if not files:
        raise SystemExit(f"no motion files in {args.folder}")
    model = build_humanoid()
    print("| file | frames | fps | up axis | import (s) | planted-foot height median, stance / constant (cm) "
          "| \\|height\\| p90, stance / constant (cm) | planted skating (cm/s) "
          "| planted feet > 1 cm / > 2 cm above the floor, planted / legs as read (%) "
          "| balance: CoP > 10 cm outside / no foot down, as read / planted (%) "
          "| hinge values fitted into range / left outside (%) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    medians, followable, floating, ranges = [], 0, [], []
    low, high = hinge_ranges().T
    for file in files:
        start = time.perf_counter()
        read = read_motion(file, model=model)
        seconds = time.perf_counter() - start
        constant = read_motion(file, grounding="constant", model=model)
        planted = read_motion(file, model=model, plant_feet=True).motion
        shares = [floating_share(m, model, h) for m in (planted, read.motion) for h in (0.01, 0.02)]
        floating.append(shares)
        h_stance, skating = planted_foot_heights(read.motion, model)
        h_constant, _ = planted_foot_heights(constant.motion, model)
        medians.append(np.median(np.abs(h_stance)))
        follow, follow_planted = followability(read.motion), followability(planted)
        followable += not follow.spans
        outside = np.mean((read.motion.dof_pos < low - 1e-9) | (read.motion.dof_pos > high + 1e-9))
        ranges.append((read.range_fit[0], outside))
        print(f"| {file.name} | {read.motion.num_frames} | {read.source_fps:g} | {read.up_axis} | {seconds:.2f} "
              f"| {100 * np.median(h_stance):.2f} / {100 * np.median(h_constant):.2f} "
              f"| {100 * np.percentile(np.abs(h_stance), 90):.2f} / {100 * np.percentile(np.abs(h_constant), 90):.2f} "
              f"| {100 * skating:.1f} | {100 * shares[0]:.1f} / {100 * shares[1]:.1f}, "
              f"{100 * shares[2]:.1f} / {100 * shares[3]:.1f} "
              f"| {100 * follow.outside:.0f} / {100 * follow.unsupported:.0f}, "
              f"{100 * follow_planted.outside:.0f} / {100 * follow_planted.unsupported:.0f} "
              f"| {100 * read.range_fit[0]:.1f} / {100 * outside:.1f} |")
    medians = np.array(medians)
    print(f"\n{len(files)} files; median |planted-foot height| per file: median {100 * np.median(medians):.2f} cm, "
          f"max {100 * medians.max():.2f} cm; files within 1 cm: {int(np.sum(medians <= 0.01))}/{len(files)}; "
          f"followable on their feet (no frame span flagged): {followable}/{len(files)}")
    floating = 100 * np.array(floating)
    print(f"planted feet > 1 cm / > 2 cm above the floor, median over files: planted {np.median(floating[:, 0]):.1f} / "
          f"{np.median(floating[:, 1]):.1f} %, legs as read {np.median(floating[:, 2]):.1f} / "
          f"{np.median(floating[:, 3]):.1f} %; worst file {floating[:, 0].max():.1f} / {floating[:, 1].max():.1f} % "
          f"against {floating[:, 2].max():.1f} / {floating[:, 3].max():.1f} %")
    ranges = 100 * np.array(ranges)
    print(f"hinge values fitted into range: median {np.median(ranges[:, 0]):.1f} %, max {ranges[:, 0].max():.1f} %; "
          f"left outside: median {np.median(ranges[:, 1]):.1f} %, max {ranges[:, 1].max():.1f} %")


if __name__ == "__main__":
    main()
