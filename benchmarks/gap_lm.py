"""The fit's two Levenberg-Marquardt solvers on the same fits: MuJoCo's and the batched one.

    python benchmarks/gap_lm.py --cases 20 --models servo go2 arm rail_leg humanoid

Cases are drawn as the blind benchmark draws them (``crisp_gym.sim2real.bench``: in-library
effects with random parameters, a second effect on another joint in some multi-joint cases, a
log synthesised with them). Each case's true effect (or pair) is fitted to its log by
:class:`crisp_gym.sim2real.fit.Fitter` twice, the whole fit (the effect's multi-start grid,
refinement, restarts) with each solver: ``"mujoco"`` (``mujoco.minimize.least_squares`` with the
fitter's Jacobian) and ``"batched"`` (three damping values per iteration in one batched
rollout). On multi-joint models the first effect's per-joint variant (one parameter per joint,
a diagonal Jacobian from one rollout) is fitted too, where the library has one. Reported per
fit: the training gap each reaches (rad RMS), rollouts (windows simulated) and seconds; then
per model and overall, the medians and how often each solver's gap is within 1 % of the other's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import get_args

import numpy as np
import tyro

from crisp_gym.sim2real.bench import BenchConfig, _effect_of, _template, commands, draw_truth, scenario, synthesize
from crisp_gym.sim2real.fit import Combo, Fitter, Solver
from crisp_gym.sim2real.replay import Replayer, bind, make_windows


@dataclass(frozen=True)
class Args:
    cases: int = 12
    """Cases drawn, round-robin over the models (in-library effects only)."""
    models: tuple[str, ...] = ("servo",)
    """Bench models: servo, go2, humanoid, arm, rail_leg."""
    max_iter: int = 15
    """Iterations for both solvers (the diagnosis's default)."""
    seed: int = 0


def _fits(truth: dict, tr) -> list[tuple[str, Combo]]:
    """The truth's own effects and, on a multi-joint log, its first effect per joint."""
    parts = truth.get("parts", [truth])
    fits = [("truth", Combo(tuple(_effect_of(p) for p in parts), tr))]
    kind = type(_effect_of(parts[0]))
    if len(tr.log.joint_names) > 1 and kind.per_joint_allowed:
        fits.append(("per-joint", Combo((kind(per_joint=True),), tr)))
    return fits


def main(args: Args) -> list[dict]:
    cfg = BenchConfig(models=args.models, p_none=0.0, p_outside=0.0)
    scenarios = {m: scenario(m, cfg) for m in args.models}
    rows = []
    print("| case | model | effect | fit | params | gap mujoco | gap batched | rollouts mujoco | rollouts batched "
          "| s mujoco | s batched |\n|---|---|---|---|---|---|---|---|---|---|---|")
    for case in range(args.cases):
        sc = scenarios[args.models[case % len(args.models)]]
        rng = np.random.default_rng(args.seed + case)
        t, u = commands(sc, rng)
        truth = draw_truth(sc, _template(sc, t, u), rng, cfg)
        log = synthesize(sc, truth, t, u, 1.0, rng)
        tr = bind(log, sc.spec())
        rep = Replayer([tr], make_windows([tr], 0.5))
        label = "+".join(p["effect"] + (f"@{p['joint']}" if p.get("joint") else "") for p in truth.get("parts", [truth]))
        for kind, combo in _fits(truth, tr):
            row = {"case": case, "model": sc.name, "effect": label, "fit": kind, "params": len(combo.params)}
            for solver in get_args(Solver):
                fitter = Fitter(rep, args.max_iter, solver=solver)
                tic = time.perf_counter()
                result = fitter.fit(combo)
                row |= {f"gap_{solver}": result.train_gap, f"rollouts_{solver}": result.rollouts,
                        f"s_{solver}": time.perf_counter() - tic}
            rows.append(row)
            print(f"| {case} | {sc.name} | {label} | {kind} | {row['params']} | {row['gap_mujoco']:.4g} | "
                  f"{row['gap_batched']:.4g} | {row['rollouts_mujoco']} | {row['rollouts_batched']} | "
                  f"{row['s_mujoco']:.2f} | {row['s_batched']:.2f} |", flush=True)
    print("\n| models | fits | mujoco gap within 1 % of batched (or lower) | batched within 1 % of mujoco (or lower) "
          "| median gap ratio mujoco / batched | median rollouts mujoco / batched | median s mujoco / batched |\n"
          "|---|---|---|---|---|---|---|")
    for name in (*args.models, "all"):
        sel = [r for r in rows if name in ("all", r["model"])]
        if not sel:
            continue
        ratio = np.array([r["gap_mujoco"] / r["gap_batched"] for r in sel])
        med = {k: np.median([r[k] for r in sel]) for k in ("rollouts_mujoco", "rollouts_batched", "s_mujoco",
                                                              "s_batched")}
        print(f"| {name} | {len(sel)} | {np.sum(ratio <= 1.01)} | {np.sum(1 / ratio <= 1.01)} | {np.median(ratio):.3f} | "
              f"{med['rollouts_mujoco']:.0f} / {med['rollouts_batched']:.0f} | "
              f"{med['s_mujoco']:.2f} / {med['s_batched']:.2f} |")
    return rows


if __name__ == "__main__":
    main(tyro.cli(Args))
