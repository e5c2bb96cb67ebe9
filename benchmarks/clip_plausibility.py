"""Physical plausibility of the synthetic clips: foot skating, scene penetration, contact height, balance.

Measures every bundled clip (as loaded from disk) and freshly generated clips of each kind for
a few more seeds, and prints a Markdown table. The targets are < 1 cm/s mean skating of a
contacting foot, < 1 cm penetration, < 1 cm contact-height error, and a centre of pressure
(:mod:`crisp_gym.balance`) more than 10 cm outside the feet on < 3 % of the frames.

    python benchmarks/clip_plausibility.py [--seeds 10 11 12]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from crisp_gym.balance import motion_balance
from crisp_gym.metrics import motion_plausibility
from crisp_gym.registry import load_clip
from crisp_gym.synth.clips import BUNDLED, KINDS, make_clip


def _row(name: str, kind: str, seed: int, boxes, motion, seconds: float | None) -> str:
    p = motion_plausibility(boxes, motion)
    balance = motion_balance(motion)
    speed = np.linalg.norm(np.diff(motion.root_pos[:, :2], axis=0), axis=1) * motion.fps
    gen = f"{seconds:.2f}" if seconds is not None else "–"
    return (f"| {name} | {kind} | {seed} | {motion.duration:.1f} | {np.median(speed[speed > 0.1]):.2f} | "
            f"{p.skating.mean_speed * 100:.3f} | {p.skating.fraction_over * 100:.1f} | "
            f"{p.penetration_max * 100:.2f} | {p.penetration_mean * 100:.3f} | "
            f"{p.contact_height_mean * 100:.2f} | {p.contact_height_max * 100:.2f} | "
            f"{balance.share_outside(0.10) * 100:.1f} | {np.nanmax(balance.outside) * 100:.0f} | {gen} |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="*", default=[10, 11, 12],
                        help="extra seeds generated for every kind")
    args = parser.parse_args(argv)
    print("| clip | kind | seed | duration (s) | pelvis speed (m/s) | skating mean (cm/s) | "
          "skating > 7.5 cm/s (%) | penetration max (cm) | penetration mean (cm) | "
          "contact height mean (cm) | contact height max (cm) | CoP > 10 cm outside the feet (%) | "
          "CoP outside max (cm) | generation (s) |")
    print("|" + "---|" * 14)
    for name, (kind, seed) in BUNDLED.items():
        clip = load_clip(name)
        print(_row(f"`{name}` (bundled)", kind, seed, clip.boxes, clip.motion, None))
    for kind in KINDS:
        for seed in args.seeds:
            start = time.perf_counter()
            boxes, motion, _ = make_clip(kind, seed)
            print(_row("generated", kind, seed, boxes, motion, time.perf_counter() - start))


if __name__ == "__main__":
    main()
