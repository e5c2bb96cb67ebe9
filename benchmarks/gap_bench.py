"""Blind benchmark of the gap diagnosis: synthetic logs with a hidden effect (or none, or
one outside the library) on the servo, Go2 and humanoid models, scored against the truth.

    python benchmarks/gap_bench.py --cases 42 --out /tmp/gap_bench
"""

from __future__ import annotations

import argparse
import json

from crisp_gym.sim2real.bench import BenchConfig, run_bench


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", type=int, default=42)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", type=float, nargs="+", default=[1.0], help="encoder-noise multiples to sweep")
    ap.add_argument("--out", default="/tmp/gap_bench")
    args = ap.parse_args()
    s = run_bench(BenchConfig(cases=args.cases, seed=args.seed, noise_scales=tuple(args.noise)), args.out)
    print("| metric | value |\n|---|---|")
    for k, v in s.items():
        if not isinstance(v, dict):
            print(f"| {k} | {v if not isinstance(v, float) else round(v, 3)} |")
    print("\nby model:", json.dumps(s["by_model"]))
    print("confusion:", json.dumps(s["confusion"], indent=1))


if __name__ == "__main__":
    main()
