"""Blind benchmark of the gap diagnosis: synthetic logs with a hidden effect (or two on
different joints, none, or one outside the library) on the servo, Go2, humanoid and arm
models, scored against the truth.

    python benchmarks/gap_bench.py --cases 42 --out gap_bench
"""

from __future__ import annotations

import argparse
import json
from typing import get_args

from crisp_gym.sim2real.bench import BenchConfig, run_bench
from crisp_gym.sim2real.diagnose import DiagnoseConfig
from crisp_gym.sim2real.fit import Solver


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", type=int, default=42)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", type=float, nargs="+", default=[1.0], help="encoder-noise multiples to sweep")
    ap.add_argument("--models", nargs="+", default=list(BenchConfig.models))
    ap.add_argument("--families", nargs="*", default=[], help="draw in-library effects of these families only")
    ap.add_argument("--p-none", type=float, default=0.12)
    ap.add_argument("--p-outside", type=float, default=0.12)
    ap.add_argument("--p-compound", type=float, default=0.15, help="share of two-effect cases (multi-joint models)")
    ap.add_argument("--solver", choices=get_args(Solver), default="mujoco",
                    help="the fits' Levenberg-Marquardt (DiagnoseConfig.solver)")
    ap.add_argument("--robust-scale", type=float, default=0.0,
                    help="soft-L1 window loss at this many noise floors (DiagnoseConfig.robust_scale; 0: off)")
    ap.add_argument("--noise-weights", action="store_true",
                    help="weigh the fits' windows by their noise-only replays (DiagnoseConfig.noise_weights)")
    ap.add_argument("--no-inverse-dynamics", action="store_true",
                    help="leave out the joint model fitted from inverse dynamics (DiagnoseConfig.inverse_dynamics)")
    ap.add_argument("--out", default="gap_bench")
    args = ap.parse_args()
    cfg = BenchConfig(cases=args.cases, seed=args.seed, noise_scales=tuple(args.noise), models=tuple(args.models),
                      families=tuple(args.families), p_none=args.p_none, p_outside=args.p_outside,
                      p_compound=args.p_compound)
    s = run_bench(cfg, args.out, DiagnoseConfig(show_progress=False, solver=args.solver,
                                                   robust_scale=args.robust_scale, noise_weights=args.noise_weights,
                                                   inverse_dynamics=not args.no_inverse_dynamics))
    print("| metric | value |\n|---|---|")
    for k, v in s.items():
        if not isinstance(v, dict):
            print(f"| {k} | {v if not isinstance(v, float) else round(v, 3)} |")
    print("\nby model:", json.dumps(s["by_model"]))
    print("confusion:", json.dumps(s["confusion"], indent=1))


if __name__ == "__main__":
    main()
