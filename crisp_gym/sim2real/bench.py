"""Blind benchmark: "real" logs generated with a hidden effect, diagnosed without it.

Each case draws a model (servo pendulum, fixed-base Go2, humanoid with feet on a floor, a
6-DoF arm whose drives span two orders of magnitude, a two-joint leg on a rail that stands,
squats and stamps), a hidden effect (one of the library's
families, two of them on different joints, "none", or one *outside* the library: a spring
the model lacks, or a first-order filter on the commands), its parameters and, on
multi-joint models, the joint it acts on. A training and a held-out log are simulated
from two different random command sequences, passed through the sensor (the effect's
measurement side, encoder quantisation and noise), and only the logs and the nominal
model reach :func:`diagnose`. The truth is written to ``truth/`` and read back only to
score: identification (confusion over families), parameter error, whether the 95 %
interval holds the truth, held-out shrink, and localisation (the right joint).

Effects are drawn at realistic sizes, not tuned to be visible. The truth's own effect size
(its *signature*: the nominal model's gap on a noise-free log of the truth) decides how a
case is scored: below :data:`DETECTABLE` noise floors it is *weak* and scored apart (right
if called "none" or the right family), because no diagnosis can tell it from noise there.
The same rule holds for each part of a two-effect truth beside the other
(:func:`part_signatures`): naming only the parts that are not weak is right too, and
``identification_accuracy_strict`` in the summary scores without that allowance.
``identified_or_named_indistinguishable`` also counts an explained case right when the truth's
family is among those the diagnosis names as indistinguishable from its winner on these logs
(a support box under a foot that never leaves it is a raised ground there); the headline
accuracy does not.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import mujoco
import numpy as np
from scipy.signal import lfilter
from tqdm import tqdm

from crisp_gym.atomic import write_text
from crisp_gym.sim2real import effects as fx
from crisp_gym.sim2real.diagnose import DiagnoseConfig, Diagnosis, diagnose
from crisp_gym.sim2real.fit import Combo, gap_rms, residuals
from crisp_gym.sim2real.log import RealLog
from crisp_gym.sim2real.models import (
    ARM_JOINTS,
    GO2_JOINTS,
    HUMANOID_BENCH_JOINTS,
    RAIL_LEG_ACTUATORS,
    RAIL_LEG_JOINTS,
    SERVO_ACTUATOR,
    SERVO_JOINT,
    ServoConfig,
    build_arm_spec,
    build_humanoid_bench_spec,
    build_rail_leg_spec,
    build_servo_pendulum_spec,
    load_go2_fixed_base_spec,
)
from crisp_gym.sim2real.replay import Replayer, Trajectory, bind, make_windows, nominal_inputs

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
        p_compound: share of cases on multi-joint models with two in-library effects of
            different families on two different joints.
        go2_xml: the Go2 MJCF.
        families: draw in-library effects of these families only (empty: all).
    """

    cases: int = 42
    seed: int = 0
    noise_scales: tuple[float, ...] = (1.0,)
    models: tuple[str, ...] = ("servo", "go2", "humanoid", "arm", "rail_leg")
    p_none: float = 0.12
    p_outside: float = 0.12
    p_compound: float = 0.15
    go2_xml: Path = GO2_XML
    families: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        fx.check_families(self.families)


@dataclass(frozen=True)
class Scenario:
    """A model and how to command it: rate, duration, logged joints, actuators, base command
    and amplitude (per actuator), encoder quantum and noise, the noise of logged velocities
    (None: the log has none, as in the real servo and Go2 logs), and the spec the model is
    compiled from (hidden effects the library models only approximately are built into it)."""

    name: str
    model: mujoco.MjModel
    joints: tuple[str, ...]
    actuators: tuple[str, ...]
    rate: float
    duration: float
    base: np.ndarray
    amplitude: np.ndarray
    quantum: float
    sigma: float
    sigma_v: float | None = None
    spec: Callable[[], mujoco.MjSpec] | None = None


def scenario(name: str, cfg: BenchConfig) -> Scenario:
    specs = {"servo": partial(build_servo_pendulum_spec, ServoConfig(kp=400)),
             "go2": partial(load_go2_fixed_base_spec, cfg.go2_xml), "humanoid": build_humanoid_bench_spec,
             "arm": build_arm_spec, "rail_leg": build_rail_leg_spec}
    if name not in specs:
        raise ValueError(f"unknown bench model {name!r}; expected servo, go2, humanoid, arm or rail_leg")
    spec = specs[name]
    return replace(_scenario(name, spec().compile()), spec=spec)


def _scenario(name: str, model: mujoco.MjModel) -> Scenario:
    if name == "servo":
        return Scenario(name, model, (SERVO_JOINT,), (SERVO_ACTUATOR,), 200.0, 6.0,
                        np.zeros(1), np.full(1, 0.9), 2 * np.pi / 4096, 0.0)
    if name == "go2":
        acts = tuple(model.actuator(i).name for i in range(model.nu))
        return Scenario(name, model, GO2_JOINTS, acts, 200.0, 5.0, np.tile([0.0, 0.9, -1.8], 4), np.full(12, 0.25),
                        2 * np.pi / 32768, 2e-4)
    if name == "humanoid":
        pitch = {"Hip": -0.1, "Knee": 0.25, "Ankle": -0.1, "Toe": 0.0}
        base = np.array([pitch[j.split("_")[1]] if j.endswith("_y") else 0.0 for j in HUMANOID_BENCH_JOINTS])
        amplitude = np.array([0.2 if j.endswith("_y") else 0.06 for j in HUMANOID_BENCH_JOINTS])
        # A humanoid's joints are faster than 120 Hz can resolve from positions (feet on
        # the ground): like real robots, it logs velocities, those of a 15-bit encoder
        # differentiated at 1 kHz and low-passed by the drive (about 0.02 rad/s of noise).
        return Scenario(name, model, HUMANOID_BENCH_JOINTS, HUMANOID_BENCH_JOINTS, 120.0, 4.0, base, amplitude,
                        2 * np.pi / 32768, 2e-4, 0.02)
    if name == "arm":
        # a 14-bit encoder, as on many arm joints' motor side divided down (here: at the joint)
        base = np.array([0.0, 0.6, -1.2, 0.0, 0.6, 0.0])
        return Scenario(name, model, ARM_JOINTS, ARM_JOINTS, 200.0, 5.0, base,
                        np.array([0.6, 0.3, 0.4, 0.8, 0.5, 1.0]), 2 * np.pi / 16384, 2e-4)
    # the hip sways the foot fore and aft, the knee bends it from stance (trunk carried) to a
    # crouch deep enough that the trunk rests on its stop and the foot swings
    return Scenario(name, model, RAIL_LEG_JOINTS, RAIL_LEG_ACTUATORS, 200.0, 5.0, np.array([0.6, -1.3]),
                    np.array([0.35, 0.8]), 2 * np.pi / 16384, 2e-4)


def add_gear_play(spec: mujoco.MjSpec, joint: str, half_width: float, start: float,
                  rotor_inertia: float) -> mujoco.MjSpec:
    """A real play in ``joint``'s gear train, built into ``spec`` (in place): its actuators drive
    a rotor of their own (a hinge on the world starting at ``start``, the joint's first
    position), and a fixed tendon, rotor minus joint, limited to ±``half_width``, couples the
    two. Inside the gap the rotor turns freely and the joint feels no motor torque; at either
    end the tendon's limit takes the torque, the rotor striking it. The joint's armature (the
    motor's reflected inertia) moves to the rotor; a joint without one gets a rotor of
    ``rotor_inertia``. The bench's truth for :class:`~crisp_gym.sim2real.effects.GearPlay`,
    built here on its own so that the library's model of it is checked against another."""
    target = spec.joint(joint)
    rotor_name = f"{joint}_rotor"
    rotor = spec.worldbody.add_body(name=rotor_name, mass=1e-3, inertia=[1e-6, 1e-6, 1e-6],
                                    explicitinertial=True)
    # the rotor starts on the joint, mid-gap (``ref`` is in the spec's angle unit)
    rotor.add_joint(name=rotor_name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1],
                    armature=target.armature or rotor_inertia, ref=np.degrees(start) if spec.compiler.degree else start)
    target.armature = 0.0
    driven = [a for a in spec.actuators if a.target == joint]
    if not driven:
        raise ValueError(f"no actuator drives {joint!r}")
    for actuator in driven:
        actuator.target = rotor_name
    # as stiff as the time step allows (MuJoCo needs a time constant of at least two steps)
    play = spec.add_tendon(name=f"{joint}_play", limited=mujoco.mjtLimited.mjLIMITED_TRUE,
                           range=[-half_width, half_width], solref_limit=[2 * spec.option.timestep, 1.0])
    play.wrap_joint(rotor_name, 1.0)
    play.wrap_joint(joint, -1.0)
    return spec


def _actuator_of(sc: Scenario, joint: str) -> int:
    """The command column of the actuator that drives ``joint``."""
    m = sc.model
    return next(a for a, name in enumerate(sc.actuators) if m.joint(int(m.actuator(name).trnid[0])).name == joint)


def driven_joints(sc: Scenario) -> tuple[str, ...]:
    """The logged joints an actuator drives (effects are drawn on these)."""
    m = sc.model
    driven = {m.joint(int(m.actuator(a).trnid[0])).name for a in sc.actuators}
    return tuple(j for j in sc.joints if j in driven)


def commands(sc: Scenario, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Smooth random commands around the base posture: a few sinusoids per joint plus
    held steps, so that the log has reversals, rests, fast and slow parts."""
    t = np.arange(int(sc.duration * sc.rate)) / sc.rate
    n = len(sc.actuators)
    u = np.tile(sc.base, (len(t), 1))
    for j in range(n):
        for _ in range(3):
            f = rng.uniform(0.2, 1.5)
            u[:, j] += sc.amplitude[j] / 3 * rng.uniform(0.5, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
        steps = np.repeat(rng.uniform(-1, 1, int(sc.duration) + 1), int(sc.rate))[:len(t)]
        u[:, j] += 0.3 * sc.amplitude[j] * steps
    return t, u


def _template(sc: Scenario, t: np.ndarray, u: np.ndarray) -> Trajectory:
    """A log of commands ``u`` whose every sample is the start state: the driven joints at
    their first command, the others (a rail) at the model's rest position."""
    m = sc.model
    start = np.array([m.qpos0[m.jnt_qposadr[m.joint(j).id]] for j in sc.joints])
    for a, name in enumerate(sc.actuators):
        start[sc.joints.index(m.joint(int(m.actuator(name).trnid[0])).name)] = u[0, a]
    qpos = np.tile(start, (len(t), 1))
    log = RealLog(time=t, qpos=qpos, ctrl=u, joint_names=sc.joints, actuator_names=sc.actuators)
    return bind(log, sc.model, validate=False)


def nominal_run(sc: Scenario, t: np.ndarray, u: np.ndarray) -> Trajectory:
    """The exact, noise-free run of the nominal model on commands ``u``: the scales the
    hidden effects are drawn against (torques, speeds) come from it."""
    tr = _template(sc, t, u)
    q, v = Replayer([tr], make_windows([tr], 1.0), 2).open_loop_states(nominal_inputs([tr]))[0]
    return bind(replace(tr.log, qpos=q, qvel=v), sc.model, validate=False)


def draw_truth(sc: Scenario, tr: Trajectory, rng: np.random.Generator, cfg: BenchConfig) -> dict:
    """A hidden effect with its parameter (and joint), sized against the nominal run ``tr``
    (:func:`nominal_run`): friction and damping a fraction of the actuator torque,
    saturation below the peak demand, delays of bus/filter size, and so on."""
    roll = rng.uniform()
    if roll < cfg.p_none:
        return {"family": "none"}
    driven = driven_joints(sc)
    joint = None if len(sc.joints) == 1 else driven[int(rng.integers(len(driven)))]
    if roll < cfg.p_none + cfg.p_outside:
        kind = OUTSIDE[int(rng.integers(len(OUTSIDE)))]
        if kind == "missing_spring":
            return {"family": "outside", "kind": kind, "joint": joint or sc.joints[0],
                    "stiffness": float(rng.uniform(0.3, 0.6)), "offset": float(rng.uniform(0.3, 0.6))}
        return {"family": "outside", "kind": kind, "tau": float(rng.uniform(0.03, 0.06))}
    if len(driven) > 1 and roll < cfg.p_none + cfg.p_outside + cfg.p_compound:
        first, second = rng.choice(len(driven), 2, replace=False)
        part = _draw_effect(sc, tr, rng, cfg, driven[first], local_only=True)
        other = _draw_effect(sc, tr, rng, cfg, driven[second], local_only=True, exclude=part["family"])
        parts = [part, other]
        return {"family": "+".join(sorted({q["family"] for q in parts})), "effect": "compound", "parts": parts}
    return _draw_effect(sc, tr, rng, cfg, joint)


def _draw_effect(sc: Scenario, tr: Trajectory, rng: np.random.Generator, cfg: BenchConfig, joint: str | None,
                 local_only: bool = False, exclude: str | None = None) -> dict:
    """One in-library effect on ``joint`` where it can be confined to one (``local_only``:
    only such effects), of a family other than ``exclude``."""
    kinds = [k for k in fx.EFFECT_TYPES if k().applicable(tr) and (not cfg.families or k.family in cfg.families)
             and k.family != exclude and (not local_only or k.per_joint_allowed or k.focus_allowed)]
    if not kinds:
        raise ValueError(f"no effect of families {cfg.families} applies to the {sc.name} model")
    kind = kinds[int(rng.integers(len(kinds)))]
    local = joint is not None and (kind.per_joint_allowed or kind.focus_allowed)
    effect = kind(joints=(joint,)) if local else kind()
    cols = effect.columns(tr)
    demand = np.abs(_demand(tr, cols))
    ts = float(demand.std(axis=0).max())
    vs = fx.speed_scale(tr)[cols].max()
    lever = max(fx.lever_scale(tr)[cols].max(), 0.05)
    draws = {
        "actuator_delay": lambda: [rng.uniform(0.01, 0.05)],
        "sensor_delay": lambda: [rng.uniform(0.01, 0.05)],
        "coulomb_friction": lambda: [rng.uniform(0.15, 0.4) * ts],
        "viscous_damping": lambda: [rng.uniform(0.2, 0.6) * ts / vs],
        "armature": lambda: [rng.uniform(1.0, 3.0) * fx.inertia_scale(tr)[cols].max()],
        "pd_gain_scale": lambda: [rng.choice([rng.uniform(0.45, 0.7), rng.uniform(1.5, 2.2)])],
        "torque_saturation": lambda: [min(rng.uniform(0.5, 0.8) * float(np.percentile(demand, 98, axis=0).max())
                                          / effect._reference(tr)[cols].max(), 0.9)],
        "backlash": lambda: [rng.uniform(0.01, 0.03)],
        "gear_play": lambda: [rng.uniform(0.01, 0.03)],
        "encoder_bias": lambda: [rng.choice([-1, 1]) * rng.uniform(0.03, 0.08)],
        "mass_scale": lambda: [rng.choice([rng.uniform(0.4, 0.6), rng.uniform(1.6, 2.2)])],
        "com_shift": lambda: list(rng.choice([-1, 1], 2) * rng.uniform(0.15, 0.4, 2) * lever),
        "payload": lambda: _draw_payload(effect, tr, rng),
        # The BAM study's XL330 fit has load coefficients 0.14 (backdriven) and 0.28 (driven).
        "load_friction": lambda: [rng.uniform(0.15, 0.4)],
        "gearbox_friction": lambda: [rng.uniform(0.15, 0.35), rng.uniform(0.05, 0.2), rng.uniform(0.5, 1.5),
                                     rng.uniform(0.1, 0.3) * vs],
        "stribeck_friction": lambda: [rng.uniform(0.15, 0.4) * ts, rng.uniform(0.1, 0.3) * vs],
        "support_box": lambda: _draw_support(tr, rng),
        "ground_friction": lambda: [rng.uniform(0.05, 0.2)],
        "contact_softness": lambda: [rng.uniform(0.06, 0.12)],
        "ground_height": lambda: [rng.choice([-1, 1]) * rng.uniform(0.01, 0.025)],
        "ground_tilt": lambda: list(rng.uniform(-0.12, 0.12, 2)),
    }
    x = [float(v) for v in draws[kind.name]()]
    return {"family": kind.family, "effect": kind.name, "joint": joint if local else None, "x": x,
            "x0": [p.x0 for p in effect.params(tr)]}


def _draw_payload(effect: fx.Payload, tr: Trajectory, rng: np.random.Generator) -> list[float]:
    """A load of 30-100 % of the mass the joint moves, 0.5-1.5 reaches from the tool's centre of
    mass in a random direction (along the joint's own axis too)."""
    mass, reach = effect._scales(tr)
    direction = rng.normal(size=3)
    offset = tr.model.body_ipos[effect._tool(tr.model, tr)] + direction / np.linalg.norm(direction) * reach \
        * rng.uniform(0.5, 1.5)
    return [rng.uniform(0.3, 1.0) * mass, *offset]


def _draw_support(tr: Trajectory, rng: np.random.Generator) -> list[float]:
    """A missing box 1-3 cm high, centred near one of the points where a foot rests."""
    pts = fx.support_points(tr)
    x, y = pts[int(rng.integers(len(pts)))]
    return [rng.uniform(0.01, 0.03), x + rng.uniform(-0.03, 0.03), y + rng.uniform(-0.01, 0.01)]


def _demand(tr: Trajectory, cols: np.ndarray) -> np.ndarray:
    """(T, len(cols)) the torque the actuators demand along the run, before any force limit."""
    unlimited = tr.model.__copy__()
    unlimited.actuator_forcelimited[:] = 0
    return fx.actuator_torque(unlimited, tr, cols, tr.ctrl[::tr.nsub], tr.enabled, tr.log.qpos, tr.qvel)


def _effect_of(truth: dict) -> fx.Effect:
    kind = next(k for k in fx.EFFECT_TYPES if k.name == truth["effect"])
    return kind(joints=(truth["joint"],)) if truth.get("joint") else kind()


def synthesize(sc: Scenario, truth: dict, t: np.ndarray, u: np.ndarray, noise: float,
               rng: np.random.Generator) -> RealLog:
    """The "real" log: the nominal model with the hidden effect, seen by a noisy encoder."""
    tr = _template(sc, t, u)
    parts = [] if truth["family"] in ("none", "outside") else truth.get("parts", [truth])
    gears = [part for part in parts if part["effect"] == "gear_play"]
    if gears:  # built into the model (a rotor and a gap), not the library's approximation of it
        spec = sc.spec()
        inertia = fx.inertia_scale(tr)
        for part in gears:
            for joint in [part["joint"]] if part["joint"] else driven_joints(sc):
                c = sc.joints.index(joint)
                # a joint without armature: a rotor light enough to add almost nothing engaged
                add_gear_play(spec, joint, part["x"][0], tr.log.qpos[0, c], 0.01 * inertia[c])
        tr = bind(tr.log, spec.compile(), validate=False)
        parts = [part for part in parts if part["effect"] != "gear_play"]
    rep = Replayer([tr], make_windows([tr], 1.0), 2)
    combo = Combo(tuple(_effect_of(part) for part in parts), tr)
    x = np.concatenate([part["x"] for part in parts]) if parts else np.zeros(0)
    inputs = combo.inputs(x, [tr])
    if truth.get("kind") == "missing_spring":
        model = inputs.models[0].__copy__()
        jid = model.joint(truth["joint"]).id
        ts = fx.torque_scale(tr)[sc.joints.index(truth["joint"])]
        model.jnt_stiffness[jid] = truth["stiffness"] * ts / 0.1
        model.qpos_spring[model.jnt_qposadr[jid]] = u[:, _actuator_of(sc, truth["joint"])].mean() + truth["offset"]
        inputs.models[0] = model
    elif truth.get("kind") == "command_filter":
        h = sc.model.opt.timestep if tr.nsub == 1 else (t[1] - t[0]) / tr.nsub
        a = np.exp(-h / truth["tau"])
        inputs.ctrl[0] = lfilter([1 - a], [1, -a], inputs.ctrl[0] - inputs.ctrl[0][0], axis=0) + inputs.ctrl[0][0]
    q, v = rep.open_loop_states(inputs)[0]
    for e, xe in zip(combo.effects, combo.split(x)):
        q, v = e.measure(q, xe, tr), e.measure_velocity(v, xe, tr)
    if noise > 0:  # noise 0: the exact signal, for the truth's own effect size
        q = q + rng.normal(0.0, sc.sigma * noise, q.shape)
        q = np.round(q / (sc.quantum * noise)) * sc.quantum * noise
        v = v + rng.normal(0.0, (sc.sigma_v or 0.0) * noise, v.shape)
    return replace(tr.log, qpos=q, qvel=None if sc.sigma_v is None else v, meta={"format": "bench"})


def signature(sc: Scenario, log: RealLog, window_s: float) -> float:
    """The truth's own effect size: the windowed RMS gap of the nominal model on a
    noise-free log of the truth (what the gap would be with a perfect sensor)."""
    tr = bind(log, sc.model, validate=False)
    rep = Replayer([tr], make_windows([tr], window_s), 2)
    return gap_rms(residuals(rep, [nominal_inputs([tr])])[0], rep.mask)


def part_signatures(sc: Scenario, truth: dict, log: RealLog, window_s: float) -> list[float]:
    """Each part's own size beside the others, for a truth of several effects: the windowed
    RMS gap, on a noise-free log of the truth, of the model that carries every *other* part
    at its true value (empty for a single effect). A gear play among the others is replayed
    by the library's own (its rotor's inertia may differ from the truth's)."""
    parts = truth.get("parts", [])
    if not parts:
        return []
    tr = bind(log, sc.spec(), validate=False)
    rep = Replayer([tr], make_windows([tr], window_s), 2)
    sizes = []
    for i in range(len(parts)):
        others = [part for j, part in enumerate(parts) if j != i]
        combo = Combo(tuple(_effect_of(part) for part in others), tr)
        x = np.concatenate([part["x"] for part in others])
        sizes.append(gap_rms(residuals(rep, [combo.inputs(x, [tr])])[0], rep.mask))
    return sizes


DETECTABLE = float(np.sqrt(DiagnoseConfig().none_factor ** 2 - 1.0))
"""An in-library effect is *weak* when its signature is below this many noise floors. With
independent noise the measured gap is sqrt(signature^2 + floor^2), and the diagnosis says
"none" below ``none_factor`` floors: a weaker effect cannot be told from noise at this SNR."""

MAGNITUDE = {"support_box": ("height",), "stribeck_friction": ("static",), "gearbox_friction": ("motor", "external")}
"""Effects whose parameter error is that of their size only: the box's position is scored
in metres apart, and a Stribeck velocity is undefined without a Stribeck torque (the gearbox's
rest factor trades against its velocity)."""


def score_case(truth: dict, result: Diagnosis) -> dict:
    """Compare a diagnosis with the truth it never saw.

    Parameter error: |x_fit - x_true| / |x_true - x_nominal| over the effect's parameters
    (vector norms; for ``MAGNITUDE`` effects, their size parameters only)."""
    verdict = result.verdict
    sel = result.selected
    predicted = {"none": "none", "unexplained": "unexplained"}.get(verdict, sel["family"] if sel else "unexplained")
    expected = {"none": "none", "outside": "unexplained"}.get(truth["family"], truth["family"])
    weak = expected not in ("none", "unexplained") and truth["signature"] < DETECTABLE * result.noise_floor
    acceptable = {expected, "none"} if weak else {expected}
    parts = truth.get("parts", [])
    weak_parts = [size < DETECTABLE * result.noise_floor for size in truth.get("part_signatures", [])]
    if any(weak_parts):  # a part too weak to see beside the others: naming the others is right too
        strong = {part["family"] for part, w in zip(parts, weak_parts) if not w}
        acceptable |= {"+".join(sorted(strong))} if strong else {part["family"] for part in parts}
    # the winner, or a family the diagnosis names as indistinguishable from it on these logs
    named = {predicted} | ({o["family"] for o in sel["indistinguishable"]} if verdict == "explained" else set())
    row = {"truth": expected, "verdict": verdict, "predicted": predicted, "weak": bool(weak),
           "weak_parts": int(sum(weak_parts)),
           "correct": predicted in acceptable, "correct_strict": predicted == expected,
           "correct_or_indistinguishable": bool(named & acceptable),
           "indistinguishable": len(named) - 1,
           "signature": truth["signature"], "shrink": result.shrink, "gap_before": result.gap_before,
           "floor": result.noise_floor, "param_error": None, "ci_contains": None, "location_error_m": None,
           "localised": None}
    if truth.get("joint") and truth["family"] not in ("none",):
        row["localised"] = result.where["worst_joint"] == truth["joint"]
    if predicted == expected and sel and "x" in truth:
        params = [p for p in sel["parameters"] if p["effect"].startswith(truth["effect"])]
        if not params and len(sel["parameters"]) == len(truth["x"]):
            params = sel["parameters"]  # another effect of the family, same parameters (the two delays)
        if truth.get("joint"):
            specific = [p for p in params if p["name"].endswith("@" + truth["joint"])]
            params = specific or params
        if len(params) == len(truth["x"]):
            names = [p["name"].split("@")[0] for p in params]
            size = [i for i, n in enumerate(names) if n in MAGNITUDE.get(truth["effect"], names)]
            fit = np.array([p["value"] for p in params])
            xt, x0 = np.array(truth["x"]), np.array(truth["x0"])
            row["param_error"] = float(np.linalg.norm((fit - xt)[size]) / max(np.linalg.norm((xt - x0)[size]), 1e-12))
            row["ci_contains"] = bool(all(params[i]["ci95"][0] <= xt[i] <= params[i]["ci95"][1] for i in size))
            if truth["effect"] == "support_box":
                row["location_error_m"] = float(np.linalg.norm((fit - xt)[1:]))
    return row


def run_bench(cfg: BenchConfig, out_dir: str | Path, dcfg: DiagnoseConfig | None = None) -> dict:
    """Run the benchmark with the diagnosis settings ``dcfg`` (default: the defaults, without
    progress bars); write ``truth/``, ``results.jsonl`` and ``summary.json``."""
    out = Path(out_dir)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    scenarios = {m: scenario(m, cfg) for m in cfg.models}
    rows = []
    dcfg = dcfg or DiagnoseConfig(show_progress=False)
    for i in tqdm(range(cfg.cases), desc="bench"):
        rng = np.random.default_rng(cfg.seed + i)
        sc = scenarios[cfg.models[i % len(cfg.models)]]
        noise = cfg.noise_scales[(i // len(cfg.models)) % len(cfg.noise_scales)]
        t, u_train = commands(sc, rng)
        _, u_test = commands(sc, rng)
        truth = draw_truth(sc, nominal_run(sc, t, u_train), rng, cfg)
        train = synthesize(sc, truth, t, u_train, noise, rng)
        test = synthesize(sc, truth, t, u_test, noise, rng)
        exact = synthesize(sc, truth, t, u_test, 0.0, rng)
        size = signature(sc, exact, dcfg.window_s)
        sizes = part_signatures(sc, truth, exact, dcfg.window_s)
        write_text(out / "truth" / f"case{i:03d}.json", json.dumps(
            {**truth, "model": sc.name, "noise": noise, "signature": size, "part_signatures": sizes}))
        result = diagnose([(train, sc.spec())], [(test, sc.spec())], dcfg)  # the truth stays on disk
        row = {"case": i, "model": sc.name, "noise": noise, "hidden": truth.get("effect", truth.get("kind", "none")),
               "selected": (result.selected or {}).get("effect"), "seconds": result.seconds,
               **score_case(json.loads((out / "truth" / f"case{i:03d}.json").read_text()), result)}
        rows.append(row)
        with open(out / "results.jsonl", "a" if i else "w") as f:
            f.write(json.dumps(row) + "\n")
    summary = summarize(rows)
    write_text(out / "summary.json", json.dumps(summary, indent=1))
    return summary


def summarize(rows: list[dict]) -> dict:
    """The benchmark's headline numbers and confusion matrix. In-library cases are split
    into detectable ones (the headline accuracy) and *weak* ones (signature below
    :data:`DETECTABLE` floors; correct if called "none" or the right family)."""
    inlib = [r for r in rows if r["truth"] not in ("none", "unexplained") and not r["weak"]]
    weak = [r for r in rows if r["weak"]]
    none = [r for r in rows if r["truth"] == "none"]
    outside = [r for r in rows if r["truth"] == "unexplained"]
    perr = [r["param_error"] for r in inlib if r["param_error"] is not None]
    cis = [r["ci_contains"] for r in inlib if r["ci_contains"] is not None]
    loc = [r["localised"] for r in inlib if r["localised"] is not None]
    box = [r["location_error_m"] for r in inlib if r["location_error_m"] is not None]
    confusion = Counter(f"{r['truth']}{' (weak)' if r['weak'] else ''} -> {r['predicted']}" for r in rows)
    return {
        "cases": len(rows),
        "identification_accuracy": _mean([r["correct"] for r in inlib]),
        "identification_accuracy_strict": _mean([r.get("correct_strict", r["correct"]) for r in inlib]),
        "identified_or_named_indistinguishable": _mean([r["correct_or_indistinguishable"] for r in inlib]),
        "indistinguishable_named_per_explained_case": (
            float(np.mean([r["indistinguishable"] for r in rows if r["verdict"] == "explained"]))
            if any(r["verdict"] == "explained" for r in rows) else None),
        "compound_with_weak_part": sum(1 for r in inlib if r.get("weak_parts")),
        "false_positive_rate_on_none": _mean([not r["correct"] for r in none]),
        "outside_reported_unexplained": _mean([r["correct"] for r in outside]),
        "weak_called_none_or_right": _mean([r["correct"] for r in weak]),
        "param_error_median": float(np.median(perr)) if perr else None,
        "ci_contains_truth": _mean(cis),
        "heldout_shrink_median": float(np.median([r["shrink"] for r in inlib])) if inlib else None,
        "localisation_accuracy": _mean(loc),
        "support_box_location_error_m": box,
        "by_model": {m: _mean([r["correct"] for r in rows if r["model"] == m]) for m in sorted({r["model"] for r in rows})},
        "confusion": dict(sorted(confusion.items())),
        "counts": {"in_library": len(inlib), "weak": len(weak), "none": len(none), "outside": len(outside)},
        "median_seconds": float(np.median([r["seconds"] for r in rows])) if rows else None,
    }


def _mean(values: list[bool]) -> float | None:
    return float(np.mean(values)) if values else None
