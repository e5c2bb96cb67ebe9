"""Speed of a full diagnosis: a 30 s, 12-joint log (the Go2 model, synthetic commands,
a hidden friction) with the whole effect library, on 2 threads.

    python benchmarks/gap_speed.py
"""

from __future__ import annotations

import time

import numpy as np

from crisp_gym.sim2real.bench import BenchConfig, commands, scenario, synthesize
from crisp_gym.sim2real.diagnose import DiagnoseConfig, diagnose


def main() -> None:
    sc = scenario("go2", BenchConfig())
    sc = type(sc)(**{**sc.__dict__, "duration": 30.0})
    rng = np.random.default_rng(0)
    t, u = commands(sc, rng)
    truth = {"family": "coulomb_friction", "effect": "coulomb_friction", "joint": "FL_calf_joint", "x": [0.5],
             "x0": [0.0]}
    log = synthesize(sc, truth, t, u, 1.0, rng)
    t0 = time.perf_counter()
    res = diagnose([(log, sc.model)], None, DiagnoseConfig(nthread=2, show_progress=False))
    dt = time.perf_counter() - t0
    print("| log | joints | candidates fitted | window rollouts | seconds | verdict |")
    print("|---|---|---|---|---|---|")
    print(f"| 30 s at 200 Hz | 12 | {len(res['ranking'])} | {res['rollouts']} | {dt:.1f} | "
          f"{res['verdict']}: {(res['selected'] or res['closest'])['effect']} |")


if __name__ == "__main__":
    main()
