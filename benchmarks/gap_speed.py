"""Speed of a full diagnosis: a 30 s, 12-joint log (the Go2 model, synthetic commands,
a hidden friction) with the whole effect library, on 2 threads.

The machine may be shared, so the time is also given as a multiple of a baseline measured
in the same run: one plain batched replay of all the log's windows with the nominal model
(the unit of work every fit repeats), and as CPU time (both rollout threads summed), which
other jobs on the machine inflate much less than wall time. With several solvers the runs
alternate between them, ``--rounds`` times, and the medians are compared.

    python benchmarks/gap_speed.py --solvers mujoco batched --rounds 3
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import tyro

from crisp_gym.sim2real.bench import BenchConfig, commands, scenario, synthesize
from crisp_gym.sim2real.diagnose import DiagnoseConfig, diagnose
from crisp_gym.sim2real.fit import Solver
from crisp_gym.sim2real.replay import Replayer, bind, make_windows, nominal_inputs


def baseline_seconds(log, model, window_s: float, repeats: int = 5) -> float:
    """Median time of one batched replay of every window of ``log`` (nominal model)."""
    tr = bind(log, model)
    rep = Replayer([tr], make_windows([tr], window_s), 2)
    inputs = nominal_inputs([tr])
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        rep.simulate([inputs])
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


@dataclass(frozen=True)
class Args:
    solvers: tuple[Solver, ...] = ("mujoco",)
    """The fits' solvers (``DiagnoseConfig.solver``), run in turn."""
    rounds: int = 1
    """Runs of each solver."""


def main(args: Args) -> None:
    sc = replace(scenario("go2", BenchConfig()), duration=30.0)
    rng = np.random.default_rng(0)
    t, u = commands(sc, rng)
    truth = {"family": "coulomb_friction", "effect": "coulomb_friction", "joint": "FL_calf_joint", "x": [0.5],
             "x0": [0.0]}
    log = synthesize(sc, truth, t, u, 1.0, rng)
    print("| solver | candidates fitted | window rollouts | wall (s) | CPU, both threads (s) | one plain replay (s) "
          "| wall / replay | verdict |")
    print("|---|---|---|---|---|---|---|---|")
    walls: dict[str, list[float]] = {solver: [] for solver in args.solvers}
    for _ in range(args.rounds):
        for solver in args.solvers:
            cfg = DiagnoseConfig(nthread=2, show_progress=False, solver=solver)
            base_before = baseline_seconds(log, sc.model, cfg.window_s)
            t0, c0 = time.perf_counter(), time.process_time()
            res = diagnose([(log, sc.spec())], None, cfg)
            seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
            base = 0.5 * (base_before + baseline_seconds(log, sc.model, cfg.window_s))
            walls[solver].append(seconds)
            print(f"| {solver} | {len(res.ranking)} | {res.rollouts} | {seconds:.1f} | {cpu:.1f} | {base:.3f} | "
                  f"{seconds / base:.0f} | {res.verdict}: {(res.selected or res.closest)['effect']} |", flush=True)
    print("\n" + ", ".join(f"{solver}: median {np.median(w):.1f} s" for solver, w in walls.items()))


if __name__ == "__main__":
    main(tyro.cli(Args))
