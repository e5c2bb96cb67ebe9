"""The diagnosis's own Levenberg-Marquardt against ``mujoco.minimize.least_squares``, on the same fits.

    python benchmarks/gap_lm.py --cases 12

Cases are drawn as the blind benchmark draws them (``crisp_gym.sim2real.bench``: an in-library
effect with random parameters on the servo model, a log synthesised with it). Each case's true
effect is fitted to that log twice, from the same best start (the effect's own start points,
scored by one batched rollout): by :class:`crisp_gym.sim2real.fit.Fitter`, the project's
Levenberg-Marquardt (one batched rollout per Jacobian and per set of trial steps), and by MuJoCo's
``least_squares`` with the same bounds and a vectorised residual (its finite-difference Jacobian
is one batched rollout too). Reported per case: the training gap each reaches (rad RMS),
rollouts (windows simulated) and seconds; and the medians.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import tyro
from mujoco import minimize

from crisp_gym.sim2real.bench import BenchConfig, _effect_of, _template, commands, draw_truth, scenario, synthesize
from crisp_gym.sim2real.fit import Combo, Fitter, gap_rms, residuals
from crisp_gym.sim2real.replay import Replayer, bind, make_windows


@dataclass(frozen=True)
class Args:
    cases: int = 12
    """Cases drawn (servo model, in-library effects)."""
    max_iter: int = 15
    """Iterations for both optimisers (the diagnosis's default)."""
    seed: int = 0


def _mujoco_fit(rep: Replayer, combo: Combo, x0: np.ndarray, max_iter: int) -> tuple[np.ndarray, int]:
    """``least_squares`` from ``x0`` within the parameters' bounds; the fit and its rollouts."""
    params = combo.params
    lo, hi = np.array([p.lo for p in params]), np.array([p.hi for p in params])
    count = [0]

    def residual(x: np.ndarray) -> np.ndarray:  # x: (n, k) columns, evaluated in one batch
        count[0] += x.shape[1] * len(rep.windows)
        r = residuals(rep, [combo.inputs(x[:, j], rep.trajs) for j in range(x.shape[1])])
        return r.reshape(r.shape[0], -1).T

    x, _ = minimize.least_squares(x0, residual, bounds=[lo, hi], max_iter=max_iter, verbose=0,
                                  x_scale=np.array([p.step for p in params]) * 100)
    return x, count[0]


def main(args: Args) -> list[dict]:
    rng = np.random.default_rng(args.seed)
    cfg = BenchConfig(models=("servo",), p_none=0.0, p_outside=0.0)
    sc = scenario("servo", cfg)
    rows = []
    for case in range(args.cases):
        t, u = commands(sc, rng)
        truth = draw_truth(sc, _template(sc, t, u), rng, cfg)
        log = synthesize(sc, truth, t, u, 1.0, rng)
        tr = bind(log, sc.model)
        rep = Replayer([tr], make_windows([tr], 0.5))
        combo = Combo((_effect_of(truth),), tr)
        fitter = Fitter(rep, args.max_iter)
        tic = time.perf_counter()
        ours = fitter.fit(combo)
        ours_s = time.perf_counter() - tic

        tic = time.perf_counter()
        params = combo.params
        starts = [np.clip(s, [p.lo for p in params], [p.hi for p in params]) for s in combo.starts()]
        r = residuals(rep, [combo.inputs(s, rep.trajs) for s in starts])
        x0 = starts[int(np.argmin([gap_rms(ri, rep.mask) for ri in r]))]
        x, theirs_rollouts = _mujoco_fit(rep, combo, x0, args.max_iter)
        theirs_rollouts += len(starts) * len(rep.windows)  # scoring the starts, as Fitter.fit counts it
        theirs_s = time.perf_counter() - tic
        theirs_gap = gap_rms(residuals(rep, [combo.inputs(x, rep.trajs)])[0], rep.mask)
        rows.append({"case": case, "effect": truth["effect"], "ours_gap": ours.train_gap, "mujoco_gap": theirs_gap,
                     "ours_rollouts": ours.rollouts, "mujoco_rollouts": theirs_rollouts, "ours_s": ours_s,
                     "mujoco_s": theirs_s})
        print(f"| {case} | {truth['effect']} | {ours.train_gap:.3g} | {theirs_gap:.3g} | {ours.rollouts} | "
              f"{theirs_rollouts} | {ours_s:.2f} | {theirs_s:.2f} |", flush=True)
    ratio = np.median([r["mujoco_gap"] / r["ours_gap"] for r in rows])
    median = {key: np.median([r[key] for r in rows]) for key in rows[0] if key.endswith(("rollouts", "_s"))}
    print(f"\nmedian gap ratio mujoco/ours {ratio:.3f}; median rollouts {median['ours_rollouts']:.0f} / "
          f"{median['mujoco_rollouts']:.0f}; median seconds {median['ours_s']:.2f} / {median['mujoco_s']:.2f}")
    return rows


if __name__ == "__main__":
    main(tyro.cli(Args))
