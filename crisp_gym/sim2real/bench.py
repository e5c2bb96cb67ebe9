"""Blind benchmark: "real" logs generated with a hidden effect, diagnosed without it.

Each case draws a model (servo pendulum, fixed-base Go2, humanoid with feet on a floor),
a hidden effect (one of the library's families, "none", or one *outside* the library:
a spring the model lacks, or a first-order filter on the commands), its parameter and,
on multi-joint models, the joint it acts on. A training and a held-out log are simulated
from two different random command sequences, passed through the sensor (the effect's
measurement side, encoder quantisation and noise), and only the logs and the nominal
model reach :func:`diagnose`. The truth is written to ``truth/`` and read back only to
score: identification (confusion over families), parameter error, whether the 95 %
interval holds the truth, held-out shrink, and localisation (the right joint).
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np
from scipy.signal import lfilter
from tqdm import tqdm

from crisp_gym.sim2real import effects as fx
from crisp_gym.sim2real.diagnose import DiagnoseConfig, diagnose
from crisp_gym.sim2real.fit import Combo
from crisp_gym.sim2real.log import RealLog
from crisp_gym.sim2real.models import (GO2_JOINTS, HUMANOID_BENCH_JOINTS, SERVO_ACTUATOR, SERVO_JOINT,
                                       ServoConfig, build_humanoid_bench, build_servo_pendulum, load_go2_fixed_base)
from crisp_gym.sim2real.replay import Replayer, Trajectory, bind, make_windows

OUTSIDE = ("missing_spring", "command_filter")
GO2_XML = Path(__file__).resolve().parents[3] / "shared" / "data" / "go2_fixed_base" / "go2.xml"


@dataclass(frozen=True)
class BenchConfig:
    """Settings of the blind benchmark.

    Attributes:
        cases: number of cases (spread round-robin over ``models``).
        seed: master seed; case ``i`` uses ``seed + i``.
        noise_scales: multiples of the encoder noise, swept case by case.
        models: which bundled models to use.
        p_none: share of cases without any effect.
        p_outside: share of cases with an effect outside the library.
        go2_xml: the Go2 MJCF.
    """

    cases: int = 42
    seed: int = 0
    noise_scales: tuple[float, ...] = (1.0,)
    models: tuple[str, ...] = ("servo", "go2", "humanoid")
    p_none: float = 0.12
    p_outside: float = 0.12
    go2_xml: Path = GO2_XML


@dataclass(frozen=True)
class Scenario:
    """A model and how to command it: rate, duration, joints, base posture, amplitude,
    encoder quantum and noise."""

    name: str
    model: mujoco.MjModel
    joints: tuple[str, ...]
    actuators: tuple[str, ...]
    rate: float
    duration: float
    base: np.ndarray
    amplitude: float
    quantum: float
    sigma: float


def scenario(name: str, cfg: BenchConfig) -> Scenario:
    if name == "servo":
        return Scenario(name, build_servo_pendulum(ServoConfig(kp=400)), (SERVO_JOINT,), (SERVO_ACTUATOR,), 200.0, 6.0,
                        np.zeros(1), 0.9, 2 * np.pi / 4096, 0.0)
    if name == "go2":
        model = load_go2_fixed_base(cfg.go2_xml)
        acts = tuple(model.actuator(i).name for i in range(model.nu))
        return Scenario(name, model, GO2_JOINTS, acts, 200.0, 5.0, np.tile([0.0, 0.9, -1.8], 4), 0.25,
                        2 * np.pi / 32768, 2e-4)
    if name == "humanoid":
        model = build_humanoid_bench()
        return Scenario(name, model, HUMANOID_BENCH_JOINTS, HUMANOID_BENCH_JOINTS, 120.0, 4.0,
                        np.array([-0.1, 0.25, -0.1, -0.1, 0.25, -0.1]), 0.2, 2 * np.pi / 32768, 2e-4)
    raise ValueError(f"unknown bench model {name!r}; expected servo, go2 or humanoid")


def commands(sc: Scenario, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Smooth random commands around the base posture: a few sinusoids per joint plus
    held steps, so that the log has reversals, rests, fast and slow parts."""
    t = np.arange(int(sc.duration * sc.rate)) / sc.rate
    n = len(sc.joints)
    u = np.tile(sc.base, (len(t), 1))
    for j in range(n):
        for _ in range(3):
            f = rng.uniform(0.2, 1.5)
            u[:, j] += sc.amplitude / 3 * rng.uniform(0.5, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
        steps = np.repeat(rng.uniform(-1, 1, int(sc.duration) + 1), int(sc.rate))[:len(t)]
        u[:, j] += 0.3 * sc.amplitude * steps
    return t, u


def _template(sc: Scenario, t: np.ndarray, u: np.ndarray) -> Trajectory:
    qpos = np.tile(u[0], (len(t), 1))
    log = RealLog(time=t, qpos=qpos, ctrl=u, joint_names=sc.joints, actuator_names=sc.actuators)
    return bind(log, sc.model, validate=False)


def draw_truth(sc: Scenario, tr: Trajectory, rng: np.random.Generator, cfg: BenchConfig) -> dict:
    """A hidden effect with its parameter (and joint), realistic and visible."""
    roll = rng.uniform()
    if roll < cfg.p_none:
        return {"family": "none"}
    joint = None if len(sc.joints) == 1 else sc.joints[int(rng.integers(len(sc.joints)))]
    if roll < cfg.p_none + cfg.p_outside:
        kind = OUTSIDE[int(rng.integers(len(OUTSIDE)))]
        if kind == "missing_spring":
            return {"family": "outside", "kind": kind, "joint": joint or sc.joints[0],
                    "stiffness": float(rng.uniform(0.3, 0.6)), "offset": float(rng.uniform(0.3, 0.6))}
        return {"family": "outside", "kind": kind, "tau": float(rng.uniform(0.03, 0.06))}
    kinds = [k for k in fx.EFFECT_TYPES if k().applicable(tr)]
    kind = kinds[int(rng.integers(len(kinds)))]
    local = joint is not None and kind.per_joint_allowed
    effect = kind(joints=(joint,)) if local else kind()
    cols = effect.columns(tr)
    ts = fx.torque_scale(tr)[cols].max()
    draws = {
        "actuator_delay": lambda: [rng.uniform(0.01, 0.05)],
        "sensor_delay": lambda: [rng.uniform(0.01, 0.05)],
        "coulomb_friction": lambda: [rng.uniform(0.15, 0.4) * ts],
        "viscous_damping": lambda: [rng.uniform(0.2, 0.6) * ts / fx.speed_scale(tr)[cols].max()],
        "armature": lambda: [rng.uniform(1.0, 3.0) * fx.inertia_scale(tr)[cols].max()],
        "pd_gain_scale": lambda: [rng.choice([rng.uniform(0.45, 0.7), rng.uniform(1.5, 2.2)])],
        "torque_saturation": lambda: [rng.uniform(0.5, 0.8) * _peak_torque(tr, cols) / effect._reference(tr)[cols].max()],
        "backlash": lambda: [rng.uniform(0.01, 0.03)],
        "encoder_bias": lambda: [rng.choice([-1, 1]) * rng.uniform(0.03, 0.08)],
        "mass_scale": lambda: [rng.choice([rng.uniform(0.4, 0.6), rng.uniform(1.6, 2.2)])],
        "ground_friction": lambda: [rng.uniform(0.05, 0.2)],
        "contact_softness": lambda: [rng.uniform(0.06, 0.12)],
        "ground_height": lambda: [rng.choice([-1, 1]) * rng.uniform(0.01, 0.025)],
        "ground_tilt": lambda: list(rng.uniform(-0.12, 0.12, 2)),
    }
    x = [float(v) for v in draws[kind.name]()]
    return {"family": kind.family, "effect": kind.name, "joint": joint if local else None, "x": x,
            "x0": [p.x0 for p in effect.params(tr)]}


def _peak_torque(tr: Trajectory, cols: np.ndarray) -> float:
    """A PD-torque scale of the commands (95th percentile of kp x command step)."""
    kp = np.abs(tr.model.actuator_biasprm[tr.act[cols], 1])
    du = np.abs(np.diff(tr.ctrl[::tr.nsub][:, tr.act[cols]], axis=0)).max(axis=0) * 10 + 0.1
    return float(np.max(kp * du))


def _effect_of(truth: dict) -> fx.Effect:
    kind = next(k for k in fx.EFFECT_TYPES if k.name == truth["effect"])
    return kind(joints=(truth["joint"],)) if truth.get("joint") else kind()


def synthesize(sc: Scenario, truth: dict, t: np.ndarray, u: np.ndarray, noise: float,
               rng: np.random.Generator) -> RealLog:
    """The "real" log: the nominal model with the hidden effect, seen by a noisy encoder."""
    tr = _template(sc, t, u)
    rep = Replayer([tr], make_windows([tr], 1.0), 2)
    if truth["family"] == "none":
        combo, x = Combo((), tr), np.zeros(0)
    elif truth["family"] == "outside":
        combo, x = Combo((), tr), np.zeros(0)
    else:
        combo, x = Combo((_effect_of(truth),), tr), np.array(truth["x"])
    inputs = combo.inputs(x, [tr])
    if truth.get("kind") == "missing_spring":
        model = inputs.models[0].__copy__()
        jid = model.joint(truth["joint"]).id
        ts = fx.torque_scale(tr)[sc.joints.index(truth["joint"])]
        model.jnt_stiffness[jid] = truth["stiffness"] * ts / 0.1
        model.qpos_spring[model.jnt_qposadr[jid]] = u[:, sc.joints.index(truth["joint"])].mean() + truth["offset"]
        inputs.models[0] = model
    elif truth.get("kind") == "command_filter":
        h = sc.model.opt.timestep if tr.nsub == 1 else (t[1] - t[0]) / tr.nsub
        a = np.exp(-h / truth["tau"])
        inputs.ctrl[0] = lfilter([1 - a], [1, -a], inputs.ctrl[0] - inputs.ctrl[0][0], axis=0) + inputs.ctrl[0][0]
    q = rep.open_loop(inputs)[0]
    for e, xe in zip(combo.effects, combo.split(x)):
        q = e.measure(q, xe, tr)
    q = q + rng.normal(0.0, sc.sigma * noise, q.shape)
    q = np.round(q / (sc.quantum * noise)) * sc.quantum * noise
    return replace(tr.log, qpos=q, qvel=None, meta={"format": "bench"})


def score_case(truth: dict, result: dict) -> dict:
    """Compare a diagnosis with the truth it never saw."""
    verdict = result["verdict"]
    sel = result.get("selected")
    predicted = {"none": "none", "unexplained": "unexplained"}.get(verdict, sel["family"] if sel else "unexplained")
    expected = {"none": "none", "outside": "unexplained"}.get(truth["family"], truth["family"])
    row = {"truth": expected, "predicted": predicted, "correct": predicted == expected,
           "shrink": result["shrink"], "gap_before": result["gap_before"], "floor": result["noise_floor"],
           "param_error": None, "ci_contains": None, "localised": None}
    if truth.get("joint") and truth["family"] not in ("none",):
        row["localised"] = result["where"]["worst_joint"] == truth["joint"]
    if row["correct"] and sel and "x" in truth:
        params = [p for p in sel["parameters"] if p["effect"].startswith(truth["effect"])]
        if truth.get("joint"):
            specific = [p for p in params if p["name"].endswith("@" + truth["joint"])]
            params = specific or params
        errs, inside = [], []
        for p, xt, x0 in zip(params, truth["x"], truth["x0"]):
            errs.append(abs(p["value"] - xt) / max(abs(xt - x0), 1e-9))
            inside.append(p["ci95"][0] <= xt <= p["ci95"][1])
        if errs:
            row["param_error"] = float(max(errs))
            row["ci_contains"] = bool(all(inside))
    return row


def run_bench(cfg: BenchConfig, out_dir: str | Path) -> dict:
    """Run the benchmark; write ``truth/``, ``results.jsonl`` and ``summary.json``."""
    out = Path(out_dir)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    scenarios = {m: scenario(m, cfg) for m in cfg.models}
    rows = []
    dcfg = DiagnoseConfig(show_progress=False)
    for i in tqdm(range(cfg.cases), desc="bench"):
        rng = np.random.default_rng(cfg.seed + i)
        sc = scenarios[cfg.models[i % len(cfg.models)]]
        noise = cfg.noise_scales[(i // len(cfg.models)) % len(cfg.noise_scales)]
        t, u_train = commands(sc, rng)
        _, u_test = commands(sc, rng)
        truth = draw_truth(sc, _template(sc, t, u_train), rng, cfg)
        (out / "truth" / f"case{i:03d}.json").write_text(json.dumps({**truth, "model": sc.name, "noise": noise}))
        train = synthesize(sc, truth, t, u_train, noise, rng)
        test = synthesize(sc, truth, t, u_test, noise, rng)
        result = diagnose([(train, sc.model)], [(test, sc.model)], dcfg)  # the truth stays on disk
        row = {"case": i, "model": sc.name, "noise": noise, "hidden": truth.get("effect", truth.get("kind", "none")),
               "selected": (result.get("selected") or {}).get("effect"), "seconds": result["seconds"],
               **score_case(json.loads((out / "truth" / f"case{i:03d}.json").read_text()), result)}
        rows.append(row)
        with open(out / "results.jsonl", "a" if i else "w") as f:
            f.write(json.dumps(row) + "\n")
    summary = summarize(rows)
    tmp = out / "summary.json.tmp"
    tmp.write_text(json.dumps(summary, indent=1))
    tmp.replace(out / "summary.json")
    return summary


def summarize(rows: list[dict]) -> dict:
    """The benchmark's headline numbers and confusion matrix."""
    inlib = [r for r in rows if r["truth"] not in ("none", "unexplained")]
    none = [r for r in rows if r["truth"] == "none"]
    outside = [r for r in rows if r["truth"] == "unexplained"]
    perr = [r["param_error"] for r in inlib if r["param_error"] is not None]
    cis = [r["ci_contains"] for r in inlib if r["ci_contains"] is not None]
    loc = [r["localised"] for r in rows if r["localised"] is not None and r["truth"] != "unexplained"]
    confusion = Counter(f"{r['truth']} -> {r['predicted']}" for r in rows)
    return {
        "cases": len(rows),
        "identification_accuracy": _mean([r["correct"] for r in inlib]),
        "false_positive_rate_on_none": _mean([not r["correct"] for r in none]),
        "outside_reported_unexplained": _mean([r["correct"] for r in outside]),
        "param_error_median": float(np.median(perr)) if perr else None,
        "ci_contains_truth": _mean(cis),
        "heldout_shrink_median": float(np.median([r["shrink"] for r in inlib])) if inlib else None,
        "localisation_accuracy": _mean(loc),
        "by_model": {m: _mean([r["correct"] for r in rows if r["model"] == m]) for m in sorted({r["model"] for r in rows})},
        "confusion": dict(sorted(confusion.items())),
        "counts": {"in_library": len(inlib), "none": len(none), "outside": len(outside)},
        "median_seconds": float(np.median([r["seconds"] for r in rows])) if rows else None,
    }


def _mean(values: list[bool]) -> float | None:
    return float(np.mean(values)) if values else None
