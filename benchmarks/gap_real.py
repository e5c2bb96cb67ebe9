"""The gap diagnosis on real data (read from ../shared/data, never copied):

* servo (Dynamixel XL330 pendulum): fit on kp in {100, 200, 400}, hold out kp = 800, and
  the reverse split; held-out position MAE before/after and the selected effect;
* Go2 fixed base: first 70 % to fit, last 30 % to test (``--go2-holdout-blocks 3``: the last
  30 % of each third, as the log is a frequency sweep whose end is its fastest part); PD-tracking
  lag vs transport delay per joint and the dominant effect per joint.

    python benchmarks/gap_real.py --out gap_real
    python benchmarks/gap_real.py --out gap_real --only go2 --go2-holdout-blocks 3
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from crisp_gym.sim2real.adapters import load_go2_npz, load_servo_json
from crisp_gym.sim2real.diagnose import DiagnoseConfig, Diagnosis, diagnose
from crisp_gym.sim2real.report import write_report

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def mae(result: Diagnosis, key: str) -> float:
    rp = result.replay
    m = rp.mask[..., None]
    return float(np.sum(np.abs(getattr(rp, key) - rp.target) * m) / (m.sum() * rp.target.shape[-1]))


def servo(out: Path, cfg: DiagnoseConfig) -> None:
    logs = [load_servo_json(f) for f in sorted((DATA / "bam_xl330").glob("*.json"))]
    print("| fit kp | held-out kp | verdict | selected / closest effect | parameters | MAE before (rad) | "
          "MAE after (rad) | held-out RMS, selected or closest |")
    print("|---|---|---|---|---|---|---|---|")
    for fit_kp, test_kp in (((100, 200, 400), (800,)), ((800,), (100, 200, 400))):
        train = [lg for lg in logs if lg[0].meta["kp"] in fit_kp]
        test = [lg for lg in logs if lg[0].meta["kp"] in test_kp]
        res = diagnose(train, test, cfg)
        write_report(res, out / f"servo_fit{'-'.join(map(str, fit_kp))}")
        sel = res.selected or res.closest
        params = ", ".join(f"{p['name']}={p['value']:.3g} [{p['ci95'][0]:.3g}, {p['ci95'][1]:.3g}]"
                           for p in sel["parameters"])
        before = mae(res, "pred_before")
        after = mae(res, "pred_after") if res.selected else before
        print(f"| {fit_kp} | {test_kp} | {res.verdict} | {sel['effect']} | {params} | {before:.4f} | "
              f"{after:.4f} (closest: {mae(res, 'pred_after'):.4f}) | "
              f"{res.gap_before:.4f} → {sel['gap_heldout']:.4f} rad, "
              f"{100 * (1 - sel['gap_heldout'] / res.gap_before):.0f} % |")


def go2(out: Path, holdout_blocks: int, cfg: DiagnoseConfig) -> None:
    res = diagnose([load_go2_npz(DATA / "go2_fixed_base" / "traj_0.npz")], None,
                   replace(cfg, holdout_fraction=0.3, holdout_blocks=holdout_blocks))
    write_report(res, out / f"go2_blocks{holdout_blocks}")
    sel = res.selected or res.closest
    print(f"\nGo2 (held out: {res.heldout}; held-out joints {res.heldout_speed_ratio:.2f}x as fast as the fitted): "
          f"verdict {res.verdict}, {sel['effect']}; held-out RMS {res.gap_before:.4f} -> "
          f"{sel['gap_heldout']:.4f} rad, {100 * (1 - sel['gap_heldout'] / res.gap_before):.0f} % "
          f"(floor {res.noise_floor:.4f}); {res.seconds:.0f} s\n")
    rp = res.replay
    r0 = (rp.pred_before - rp.target) * rp.mask[..., None]
    before = dict(zip(res.joints, np.sqrt(np.sum(r0**2, axis=(0, 1)) / rp.mask.sum())))
    singles = [r for r in res.ranking if "+" not in r["effect"]]
    print("| joint | PD tracking lag, sim vs command (ms) | real vs command (ms) | transport delay, real vs sim (ms) | "
          "held-out gap before (rad) | dominant single effect | after (rad) | shrink |")
    print("|---|---|---|---|---|---|---|---|")
    for j, v in res.where["per_joint"].items():
        dom = min(singles, key=lambda r: r["gap_heldout_per_joint"][j])
        after = dom["gap_heldout_per_joint"][j]
        print(f"| {j} | {1e3 * v['lag_sim_vs_command_s']:.1f} | {1e3 * v['lag_real_vs_command_s']:.1f} | "
              f"{1e3 * v['lag_real_vs_sim_s']:.1f} | {before[j]:.4f} | {dom['effect']} | {after:.4f} | "
              f"{100 * (1 - after / before[j]):.0f} % |")
    print("\n| rank | effect | params | held-out gap | shrink |\n|---|---|---|---|---|")
    for i, r in enumerate(res.ranking[:8], 1):
        print(f"| {i} | {r['effect']} | {r['nparam']} | {r['gap_heldout']:.4f} | {100 * r['shrink']:.0f} % |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="gap_real")
    ap.add_argument("--only", choices=("servo", "go2"), help="run one of the two logs' diagnoses")
    ap.add_argument("--go2-holdout-blocks", type=int, default=1,
                    help="hold out the last 30 %% of each of this many parts of the Go2 log (1: its end)")
    ap.add_argument("--robust-scale", type=float, default=0.0,
                    help="soft-L1 window loss at this many noise floors (DiagnoseConfig.robust_scale; 0: off)")
    ap.add_argument("--noise-weights", action="store_true",
                    help="weigh the fits' windows by their noise-only replays (DiagnoseConfig.noise_weights)")
    ap.add_argument("--no-inverse-dynamics", action="store_true",
                    help="leave out the joint model fitted from inverse dynamics (DiagnoseConfig.inverse_dynamics)")
    args = ap.parse_args()
    cfg = DiagnoseConfig(show_progress=False, robust_scale=args.robust_scale, noise_weights=args.noise_weights,
                         inverse_dynamics=not args.no_inverse_dynamics)
    if not DATA.is_dir():
        raise SystemExit(f"real data not found at {DATA}")
    if args.only != "go2":
        servo(Path(args.out), cfg)
    if args.only != "servo":
        go2(Path(args.out), args.go2_holdout_blocks, cfg)


if __name__ == "__main__":
    main()
