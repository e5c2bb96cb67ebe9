"""Identification on logs generated with a known effect (the servo pendulum: fast)."""

import json
from dataclasses import replace
from types import SimpleNamespace

import mujoco
import numpy as np
import pytest

from crisp_gym.sim2real import effects as fx
from crisp_gym.sim2real.bench import GO2_XML, BenchConfig, commands, scenario, synthesize
from crisp_gym.sim2real.diagnose import (Candidate, DiagnoseConfig, _indistinguishable, _parsimonious_first,
                                         _per_joint_mixture, _supported, at_bound, diagnose, forward_bases, median_draw,
                                         noise_floors, noise_spread, speed_ratio)
from crisp_gym.sim2real.fit import Combo, Fitter, Frozen, chains, gap_rms, residuals, soft_l1_windows, undetermined
from crisp_gym.sim2real.log import RealLog
from crisp_gym.sim2real.models import ServoConfig, add_support_slot, build_servo_pendulum_spec
from crisp_gym.sim2real.replay import Replayer, bind, make_windows
from crisp_gym.sim2real.report import REPORT_KEYS, extrapolation_lines, write_report

CFG = DiagnoseConfig(show_progress=False)
needs_go2 = pytest.mark.skipif(not GO2_XML.is_file(), reason=f"{GO2_XML} (../shared/data) is not present")


def _case(truth: dict, seed: int = 0):
    sc = scenario("servo", BenchConfig())
    rng = np.random.default_rng(seed)
    t, u1 = commands(sc, rng)
    _, u2 = commands(sc, rng)
    return sc, synthesize(sc, truth, t, u1, 1.0, rng), synthesize(sc, truth, t, u2, 1.0, rng)


def test_delay_is_found_with_its_value():
    truth = {"family": "delay", "effect": "actuator_delay", "joint": None, "x": [0.03], "x0": [0.01]}
    sc, train, test = _case(truth)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res.verdict == "explained" and res.selected["family"] == "delay"
    p = res.selected["parameters"][0]
    assert abs(p["value"] - 0.03) < 0.003
    assert res.shrink > 0.8
    # a delay leaves load friction far down the singles: its costly directional form is not fitted
    assert not any(r["effect"].startswith("gearbox_friction") for r in res.ranking)
    assert any(s["effect"].startswith("gearbox_friction") and s["reason"].startswith("not refined")
               for s in res.skipped)


def test_no_effect_gives_none():
    sc, train, test = _case({"family": "none"}, seed=1)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res.verdict == "none"


def test_friction_value_and_interval():
    sc, train, test = _case({"family": "coulomb_friction", "effect": "coulomb_friction", "joint": None,
                             "x": [0.08], "x0": [0.0]}, seed=2)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res.selected["family"] == "coulomb_friction"
    lo, hi = res.selected["parameters"][0]["ci95"]
    assert abs(res.selected["parameters"][0]["value"] - 0.08) < 0.008 and lo <= 0.08 <= hi


def test_outside_effect_is_unexplained(tmp_path):
    sc, train, test = _case({"family": "outside", "kind": "command_filter", "tau": 0.05}, seed=3)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res.verdict == "unexplained"
    assert res.residual["joints"][0]["joint"] == sc.joints[0]
    assert sum(b["share_of_power"] for b in res.residual["bands"]) == pytest.approx(1.0)
    text = (write_report(res, tmp_path / "rep", plots=False) / "report.md").read_text()
    assert "not a cause" in text and "What remains" in text
    warned = replace(res, mujoco_warnings={"Nan, Inf or huge value in QACC at DOF N": 3})
    text = (write_report(warned, tmp_path / "warned", plots=False) / "report.md").read_text()
    assert "- 3 × Nan, Inf or huge value in QACC at DOF N" in text


@needs_go2
def test_residual_structure_finds_the_joint_and_band_of_a_known_residual():
    from crisp_gym.sim2real.gap import residual_structure

    sc = scenario("go2", BenchConfig())
    t, u = commands(sc, np.random.default_rng(0))
    tr = bind(synthesize(sc, {"family": "none"}, t, u, 0.0, np.random.default_rng(0)), sc.model, validate=False)
    rep = Replayer([tr], make_windows([tr], 0.5), 1)
    steps = np.arange(1, rep.windows.size) * tr.log.dt
    r = np.zeros((len(rep.windows), len(steps), len(sc.joints)))
    r[..., 4] = 0.01 * np.sin(2 * np.pi * 12.0 * steps)[None]  # 12 Hz on one joint
    r[..., 7] = 0.002 * np.sin(2 * np.pi * 12.0 * steps)[None]  # a little on another, below 10 % of the excess
    r *= rep.mask[..., None]
    out = residual_structure(rep, r, np.full(len(sc.joints), 1e-4))
    assert [j["joint"] for j in out["joints"]] == [sc.joints[4]]
    band = {b["from_hz"]: b["share_of_power"] for b in out["bands"]}
    assert band[8.0] > 0.9


@pytest.mark.parametrize("solver", ["mujoco", "batched"])
@pytest.mark.parametrize("kind, x", [(fx.GainScale, 0.6), (fx.MassScale, 1.8), (fx.EncoderBias, 0.05)])
def test_each_effect_fits_back(kind, x, solver):
    sc = scenario("servo", BenchConfig())
    truth = {"family": kind.family, "effect": kind.name, "joint": None, "x": [x], "x0": [0.0]}
    _, train, _ = _case(truth, seed=4)
    tr = bind(train, sc.model)
    fitter = Fitter(Replayer([tr], make_windows([tr], 0.5)), solver=solver)
    res = fitter.fit(Combo((kind(),), tr))
    assert abs(res.x[0] - x) < 0.02 * max(1.0, abs(x))


def test_a_drive_saturating_at_one_percent_of_its_limit_fits_back():
    """A joint loaded far below its model's limit saturates at a percent of it (the bench drew
    1.4 % on a humanoid's knee abduction); the fraction's bound sat at 2 % and a PD gain won."""
    sc = scenario("servo", BenchConfig())
    truth = {"family": "torque_saturation", "effect": "torque_saturation", "joint": None, "x": [0.01], "x0": [1.0]}
    _, train, _ = _case(truth, seed=4)
    tr = bind(train, sc.model)
    res = Fitter(Replayer([tr], make_windows([tr], 0.5))).fit(Combo((fx.TorqueSaturation(),), tr))
    assert res.x[0] == pytest.approx(0.01, rel=0.1)


@needs_go2
def test_both_solvers_fit_a_per_joint_effect_through_its_diagonal_jacobian():
    """Damping on one Go2 joint, fitted with a parameter per joint: each solver finds it on
    that joint (and next to nothing elsewhere) at the same gap, MuJoCo's with fewer rollouts
    than the project's own batched solver (one rollout per trial instead of three)."""
    sc = scenario("go2", BenchConfig())
    rng = np.random.default_rng(6)
    t, u = commands(sc, rng)
    joint, value = sc.joints[4], 0.4
    truth = {"family": "viscous_damping", "effect": "viscous_damping", "joint": joint, "x": [value], "x0": [0.0]}
    tr = bind(synthesize(sc, truth, t[:1200], u[:1200], 1.0, rng), sc.model)
    rep = Replayer([tr], make_windows([tr], 0.5))
    fits = {}
    for solver in ("mujoco", "batched"):
        fitter = Fitter(rep, solver=solver)
        fits[solver] = fitter.fit(Combo((fx.ViscousDamping(per_joint=True),), tr))
        x = fits[solver].x
        assert x[4] == pytest.approx(value, rel=0.1)
        assert np.abs(np.delete(x, 4)).max() < 0.1 * value
    assert fits["mujoco"].train_gap == pytest.approx(fits["batched"].train_gap, rel=0.01)
    assert fits["mujoco"].rollouts < fits["batched"].rollouts


def test_soft_l1_windows_keeps_small_windows_and_counts_large_ones_by_their_rms():
    """Each window's sum of squares becomes count·scale²·ρ(e), ρ(e) = 2(√(1+e) − 1): unchanged
    for a window far below the scale, 2·√e (its RMS over the scale, doubled) far above it; and
    the fitter's gap undoes the rescaling exactly."""
    rng = np.random.default_rng(0)
    mask = np.ones((3, 50), dtype=bool)
    mask[2, 30:] = False
    r = rng.normal(size=(3, 50, 2)) * np.array([1e-4, 1.0, 0.3])[:, None, None] * mask[..., None]
    scale = 0.01
    out = soft_l1_windows(r[None], mask, scale)[0]
    count = mask.sum(axis=1) * 2
    e = np.sum(r**2, axis=(1, 2)) / (count * scale**2)
    np.testing.assert_allclose(np.sum(out**2, axis=(1, 2)) / (count * scale**2), 2 * (np.sqrt(1 + e) - 1))
    np.testing.assert_allclose(out[0], r[0], rtol=1e-4)  # e = 1e-4: ρ(e)/e = 1 − e/4 + ...
    assert np.sum(out[1] ** 2) / (count[1] * scale**2) == pytest.approx(2 * np.sqrt(e[1]), rel=0.02)
    fitter = SimpleNamespace(robust_scale=scale, window_scale=None, rep=SimpleNamespace(mask=mask))
    assert Fitter._gap(fitter, out) == pytest.approx(gap_rms(r, mask), rel=1e-9)


def _damped_servo_with_a_jump():
    """A servo log with viscous damping 0.05, bound clean and with a 0.1 rad encoder jump
    inside its fourth window (of twelve), and those windows."""
    sc = scenario("servo", BenchConfig())
    rng = np.random.default_rng(1)
    t, u = commands(sc, rng)
    truth = {"family": "viscous_damping", "effect": "viscous_damping", "joint": None, "x": [0.05], "x0": [0.0]}
    log = synthesize(sc, truth, t, u, 1.0, rng)
    tr = bind(log, sc.model)
    windows = make_windows([tr], 0.5)
    s, n = windows.start[3], windows.length[3]
    qpos = log.qpos.copy()
    qpos[s + 3:s + n] += 0.1
    jumped = bind(replace(log, qpos=qpos), sc.model)
    return tr, jumped, windows


def test_robust_fit_is_not_pulled_by_one_corrupted_window():
    """An encoder jump of 0.1 rad inside one of a servo log's twelve windows pulls a plain
    least-squares fit of its damping 5-10 % off (measured over three seeds); counted by the
    soft-L1 loss at a few noise floors it stays within 2 % of the clean log's fit."""
    tr, jumped, windows = _damped_servo_with_a_jump()
    clean = Fitter(Replayer([tr], windows)).fit(Combo((fx.ViscousDamping(),), tr)).x[0]
    plain = Fitter(Replayer([jumped], windows)).fit(Combo((fx.ViscousDamping(),), jumped)).x[0]
    robust = Fitter(Replayer([jumped], windows), robust_scale=0.005).fit(Combo((fx.ViscousDamping(),), jumped)).x[0]
    assert abs(plain - clean) > 0.05 * clean
    assert abs(robust - clean) < 0.02 * clean
    with pytest.raises(ValueError, match="robust_scale"):
        Fitter(Replayer([tr], windows), robust_scale=0.0)


def test_a_window_scaled_down_does_not_pull_the_fit_and_the_reported_gap_is_the_plain_one():
    """The corrupted window of the test above, scaled by 0.05 (others by 1): the damping fit
    stays within 2 % of the clean log's; the training gap it reports is the plain RMS at its
    fit (the scaling undone). A scale per window is checked."""
    tr, jumped, windows = _damped_servo_with_a_jump()
    combo = Combo((fx.ViscousDamping(),), jumped)
    clean = Fitter(Replayer([tr], windows)).fit(Combo((fx.ViscousDamping(),), tr)).x[0]
    scale = np.ones(len(windows))
    scale[3] = 0.05
    rep = Replayer([jumped], windows)
    res = Fitter(rep, window_scale=scale).fit(combo)
    assert abs(res.x[0] - clean) < 0.02 * clean
    plain_gap = gap_rms(residuals(rep, [combo.inputs(res.x, rep.trajs)])[0], rep.mask)
    assert res.train_gap == pytest.approx(plain_gap, rel=1e-9)
    with pytest.raises(ValueError, match="window_scale"):
        Fitter(rep, window_scale=scale[1:])


def test_noise_weights_count_less_the_windows_where_contacts_begin():
    """Replayed under noise alone, a window in which the rail leg's foot keeps or lacks contact
    throughout replays like the typical one (full weight); the least reliable window is one
    where the foot strikes the floor. The arm, which has no contacts, keeps every window
    near full weight."""
    from crisp_gym.sim2real.diagnose import noise_weights

    for name in ("rail_leg", "arm"):
        sc = scenario(name, BenchConfig())
        rng = np.random.default_rng(0)
        t, u = commands(sc, rng)
        log = synthesize(sc, {"family": "none"}, t, u, 0.0, rng)  # the weights add the encoder's noise
        tr = bind(log, sc.model)
        windows = make_windows([tr], 0.5)
        weights = noise_weights(Replayer([tr], windows), seed=0)
        assert weights.shape == (len(windows),) and np.all((weights > 0) & (weights <= 1))
        if name == "arm":
            assert weights.min() > 0.8
            continue
        data = mujoco.MjData(tr.model)
        touching = []
        for q in log.qpos:
            data.qpos[tr.qadr] = q
            mujoco.mj_forward(tr.model, data)
            touching.append(data.ncon > 0)
        touching = np.array(touching)
        strikes = np.flatnonzero(touching[1:] & ~touching[:-1]) + 1
        counts = np.array([np.sum((strikes >= s) & (strikes < s + n)) for s, n in zip(windows.start, windows.length)])
        assert np.any(counts == 0) and np.all(weights[counts == 0] > 0.95)
        assert counts[np.argmin(weights)] > 0 and weights.min() < 0.5


def test_fitter_rejects_an_unknown_solver_and_a_step_fraction_outside_0_1():
    sc = scenario("servo", BenchConfig())
    _, train, _ = _case({"family": "none"}, seed=4)
    tr = bind(train, sc.model)
    with pytest.raises(ValueError, match="unknown solver"):
        Fitter(Replayer([tr], make_windows([tr], 0.5)), solver="scipy")
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match="step_fraction"):
            Fitter(Replayer([tr], make_windows([tr], 0.5)), step_fraction=bad)
        with pytest.raises(ValueError, match="step_fraction"):
            DiagnoseConfig(step_fraction=bad)


def test_report_files(tmp_path):
    truth = {"family": "delay", "effect": "actuator_delay", "joint": None, "x": [0.02], "x0": [0.01]}
    sc, train, test = _case(truth, seed=5)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    out = write_report(res, tmp_path / "rep")
    data = json.loads((out / "report.json").read_text())
    assert all(k in data for k in REPORT_KEYS)
    assert (out / "report.md").read_text().startswith("# Sim-to-real gap diagnosis")
    assert (out / "overlay.png").is_file() and (out / "ranking.png").is_file()


def test_cli_bench_writes_its_summary_with_the_given_diagnosis_settings(tmp_path, capsys):
    from crisp_gym.sim2real.cli import main

    out = tmp_path / "bench"
    assert main(["bench", "--cases", "1", "--models", "servo", "--config.solver", "batched", "-o", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["cases"] == 1 and json.loads(capsys.readouterr().out)["cases"] == 1
    assert len((out / "results.jsonl").read_text().splitlines()) == 1
    with pytest.raises(SystemExit):  # tyro rejects a solver that is not one
        main(["bench", "--cases", "1", "--config.solver", "scipy", "-o", str(out)])


def test_cli_errors_cleanly(tmp_path, capsys):
    from crisp_gym.sim2real.cli import main

    assert main(["diagnose", "--real", str(tmp_path / "missing.npz"), "-o", str(tmp_path / "r")]) == 2
    assert "not found" in capsys.readouterr().err


# -- effects added for load-dependent friction, mass/COM change and missing support -------------------

def _selected_value(res: dict, name: str) -> float:
    return next(p["value"] for p in res.selected["parameters"] if p["name"].split("@")[0] == name)


def test_load_friction_is_found_with_its_value():
    truth = {"family": "load_friction", "effect": "load_friction", "joint": None, "x": [0.3], "x0": [0.0]}
    sc, train, test = _case(truth, seed=6)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res.verdict == "explained" and res.selected["family"] == "load_friction"
    assert abs(_selected_value(res, "mu") - 0.3) < 0.03
    assert res.shrink > 0.8
    # load friction ranks first, so its directional form was refined from it (and not preferred)
    assert any(r["effect"].startswith("gearbox_friction") for r in res.ranking)


def test_load_friction_holds_the_joint_under_load():
    """The physics, independently of any fit: with load friction the servo sticks (stays
    put) for longer than with none, and the Coulomb friction that matches its mean
    friction torque does not reproduce the same trajectory."""
    sc = scenario("servo", BenchConfig())
    rng = np.random.default_rng(7)
    t, u = commands(sc, rng)
    logs = {mu: synthesize(sc, {"family": "load_friction", "effect": "load_friction", "joint": None, "x": [mu],
                                "x0": [0.0]}, t, u, 1e-6, rng).qpos[:, 0] for mu in (0.0, 0.4)}
    still = {mu: np.mean(np.abs(np.diff(q)) < 1e-4) for mu, q in logs.items()}
    assert still[0.4] > still[0.0] + 0.05


def test_com_shift_is_found_with_its_value():
    truth = {"family": "mass", "effect": "com_shift", "joint": None, "x": [0.02, 0.015], "x0": [0.0, 0.0]}
    sc, train, test = _case(truth, seed=8)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res.verdict == "explained" and res.selected["effect"].startswith("com_shift")
    fit = np.array([_selected_value(res, "along"), _selected_value(res, "across")])
    assert np.linalg.norm(fit - [0.02, 0.015]) < 0.1 * np.linalg.norm([0.02, 0.015])


def test_com_shift_moves_the_gravity_torque():
    """A COM shift across the lever of the pendulum changes where it hangs at rest by
    atan(across / lever), which is what the effect must do to the model."""
    import mujoco

    sc = scenario("servo", BenchConfig())
    t, u = commands(sc, np.random.default_rng(0))
    tr = bind(synthesize(sc, {"family": "none"}, t, u, 1.0, np.random.default_rng(0)), sc.model)
    model = sc.model.__copy__()
    fx.ComShift().edit_model(model, np.array([0.0, 0.02]), tr)
    model.actuator_gainprm[:] = 0.0  # actuator off: the pendulum hangs freely
    model.actuator_biasprm[:] = 0.0
    model.dof_damping[:] = 0.5
    data = mujoco.MjData(model)
    for _ in range(4000):
        mujoco.mj_step(model, data)
    assert abs(abs(data.qpos[0]) - np.arctan(0.02 / 0.1)) < 0.01


def test_stribeck_is_found_with_its_torque():
    sc = scenario("servo", BenchConfig())
    ts = 0.15
    truth = {"family": "stribeck_friction", "effect": "stribeck_friction", "joint": None, "x": [ts, 0.3],
             "x0": [0.0, 0.0]}
    _, train, test = _case(truth, seed=9)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res.verdict == "explained" and res.selected["family"] == "stribeck_friction"
    assert abs(_selected_value(res, "static") - ts) < 0.1 * ts


def _humanoid_box_case(seed: int = 0):
    sc = scenario("humanoid", BenchConfig())
    rng = np.random.default_rng(seed)
    t, u1 = commands(sc, rng)
    _, u2 = commands(sc, rng)
    truth = {"family": "support_box", "effect": "support_box", "joint": None, "x": [0.02, 0.05, 0.09]}
    return sc, synthesize(sc, truth, t, u1, 1.0, rng), synthesize(sc, truth, t, u2, 1.0, rng)


def test_support_box_height_fits_back():
    sc, train, _ = _humanoid_box_case()
    tr = bind(train, sc.model)
    fitter = Fitter(Replayer([tr], make_windows([tr], 0.5)))
    res = fitter.fit(Combo((fx.SupportBox(),), tr))
    assert abs(res.x[0] - 0.02) < 0.002
    assert np.linalg.norm(res.x[1:] - [0.05, 0.09]) < 0.05


@pytest.mark.slow
def test_support_box_is_selected_over_ground_effects():
    sc, train, test = _humanoid_box_case(seed=1)
    families = ("support_box", "ground_height", "ground_tilt", "contact_softness", "encoder_bias")
    res = diagnose([(train, sc.model)], [(test, sc.model)], DiagnoseConfig(show_progress=False, families=families))
    assert res.verdict == "explained" and res.selected["family"] == "support_box"
    assert abs(_selected_value(res, "height") - 0.02) < 0.002


def test_bench_scores_weak_effects_apart():
    """The documented rule: an in-library effect whose own noise-free gap is below
    sqrt(1.5^2 - 1) noise floors is weak; calling it "none" is then right."""
    from crisp_gym.sim2real.bench import DETECTABLE, score_case

    truth = {"family": "delay", "effect": "actuator_delay", "x": [0.01], "x0": [0.0]}
    result = SimpleNamespace(verdict="none", selected=None, noise_floor=0.01, shrink=0.0, gap_before=0.011,
                             where={"worst_joint": "servo"})  # the fields of a Diagnosis that scoring reads
    weak = score_case({**truth, "signature": 0.5 * DETECTABLE * 0.01}, result)
    strong = score_case({**truth, "signature": 2.0 * DETECTABLE * 0.01}, result)
    assert weak["weak"] and weak["correct"]
    assert not strong["weak"] and not strong["correct"]
    assert abs(DETECTABLE - np.sqrt(1.25)) < 1e-12


def test_bench_scores_a_weak_part_of_two_effects_apart():
    """The same rule per part: beside a strong delay, a friction whose own gap is below
    DETECTABLE floors cannot be seen, so naming the delay alone is right, and strict scoring
    still counts it a miss; with both parts strong the delay alone is wrong."""
    from crisp_gym.sim2real.bench import DETECTABLE, score_case

    parts = [{"family": "delay", "effect": "actuator_delay", "joint": "hip", "x": [0.02], "x0": [0.0]},
             {"family": "coulomb_friction", "effect": "coulomb_friction", "joint": "knee", "x": [0.1], "x0": [0.0]}]
    truth = {"family": "coulomb_friction+delay", "effect": "compound", "parts": parts, "signature": 0.1}
    selected = {"family": "delay", "parameters": [], "indistinguishable": []}
    result = SimpleNamespace(verdict="explained", selected=selected, noise_floor=0.01, shrink=0.9, gap_before=0.1,
                             where={"worst_joint": "hip"})
    floor = DETECTABLE * 0.01
    # part_signatures[i]: part i's size, the gap left with the other part applied
    weak_friction = score_case({**truth, "part_signatures": [5 * floor, 0.5 * floor]}, result)
    both_strong = score_case({**truth, "part_signatures": [5 * floor, 5 * floor]}, result)
    weak_delay = score_case({**truth, "part_signatures": [0.5 * floor, 5 * floor]}, result)
    assert weak_friction["correct"] and not weak_friction["correct_strict"] and weak_friction["weak_parts"] == 1
    assert not both_strong["correct"] and both_strong["weak_parts"] == 0
    assert not weak_delay["correct"]  # the delay was the part left to see: naming it alone is not enough


@needs_go2
def test_part_signatures_measure_each_part_beside_the_other():
    """A part's size beside the other is the gap the other alone leaves on the truth's exact
    log: a large friction beside a tiny bias is large, the bias beside the friction tiny."""
    from crisp_gym.sim2real.bench import part_signatures, signature

    sc = scenario("go2", BenchConfig())
    rng = np.random.default_rng(8)
    t, u = commands(sc, rng)
    t, u = t[:1000], u[:1000]
    friction = {"family": "coulomb_friction", "effect": "coulomb_friction", "joint": sc.joints[2], "x": [2.0],
                "x0": [0.0]}
    bias = {"family": "encoder_bias", "effect": "encoder_bias", "joint": sc.joints[7], "x": [1e-5], "x0": [0.0]}
    truth = {"family": "coulomb_friction+encoder_bias", "effect": "compound", "parts": [friction, bias]}
    exact = synthesize(sc, truth, t, u, 0.0, rng)
    size_friction, size_bias = part_signatures(sc, truth, exact, 0.5)
    alone = signature(sc, synthesize(sc, friction, t, u, 0.0, rng), 0.5)
    assert size_friction == pytest.approx(alone, rel=0.05)
    assert size_bias < 0.01 * size_friction  # what is left: the replay of an exact log, not the bias


def test_an_unknown_effect_family_is_named_before_any_fit():
    """``--config.families friction`` (no such family) made an empty library and an IndexError
    after the replay was set up; the config now names it and the families there are."""
    with pytest.raises(ValueError, match=r"unknown effect families \['friction'\]; the library's are delay, "):
        DiagnoseConfig(families=("friction",))
    assert DiagnoseConfig(families=("coulomb_friction",)).families == ("coulomb_friction",)


def test_a_candidate_that_cannot_act_is_skipped_with_its_reason(tmp_path):
    """The missing-support candidate raised when no geom rested on the ground at the log's mean
    posture, and the whole diagnosis ended after minutes of fitting. A log whose pendulum never
    comes near the ground now skips that one candidate, says why, and ranks the others."""
    from crisp_gym.sim2real import effects as fx

    truth = {"family": "delay", "effect": "actuator_delay", "joint": None, "x": [0.02], "x0": [0.01]}
    _, train, test = _case(truth, seed=7)
    spec = build_servo_pendulum_spec(ServoConfig(kp=400))  # the bench's servo, plus a ground 3 m below
    for geom in spec.geoms:  # a pendulum that would collide, were anything near it
        geom.contype = geom.conaffinity = 1
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=(1, 1, 0.05), pos=(0, 0, -3))
    slotted = add_support_slot(spec).compile()
    tr = bind(train, slotted)
    with pytest.raises(fx.CannotApply, match="within 12 cm of the modelled ground"):
        fx.support_points(tr)
    res = diagnose([(train, slotted)], [(test, slotted)], replace(CFG, families=("delay", "support_box")))
    assert [s["effect"] for s in res.skipped] == ["support_box[shared]"]
    assert res.verdict == "explained" and res.selected["family"] == "delay"
    assert "cannot act on these logs" in (write_report(res, tmp_path / "rep") / "report.md").read_text()


def test_fitted_parameters_at_their_bounds_are_flagged(tmp_path):
    """A fit that ends at a bound wanted to go further; the report says so instead of presenting
    the value as identified."""
    truth = {"family": "delay", "effect": "actuator_delay", "joint": None, "x": [0.02], "x0": [0.01]}
    sc, train, test = _case(truth, seed=5)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    (param,) = res.selected["parameters"]
    assert param["at_bound"] is False  # 20 ms, inside the delay's range
    bounded = fx.Param("x", 0.0, 0.0, 0.1, 1e-3, "m")
    assert at_bound(bounded, 0.1) and at_bound(bounded, 0.0005) and not at_bound(bounded, 0.05)
    assert param["identified"] is True
    res.selected["parameters"][0]["at_bound"] = True
    assert "**at its bound**" in (write_report(res, tmp_path / "rep") / "report.md").read_text()
    res.selected["parameters"][0]["identified"] = False
    report = (write_report(res, tmp_path / "rep2") / "report.md").read_text()
    assert "**not determined by the data**" in report and "**at its bound**" not in report


def test_parameters_the_residual_does_not_see_are_undetermined():
    """A parameter whose column is zero, and two that trade exactly, are undetermined; a
    parameter that is merely small in its own units but seen across its range is not."""
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(size=(3, 50))
    jac = np.stack([a, np.zeros(50), b, -2.0 * b, 1e-9 * c])
    span = np.array([1.0, 1.0, 1.0, 0.5, 1e6])  # the last: tiny per unit, but over a wide range
    assert undetermined(jac, span).tolist() == [False, True, True, True, False]
    assert undetermined(jac, np.ones(5))[4]  # over a unit range it is not seen
    assert not undetermined(np.stack([a, b]), np.ones(2)).any()


def test_a_delay_on_one_drive_is_found_on_that_drive():
    """Delay existed only shared by every drive: a single slow servo (here the left hip's flexion,
    40 ms) now is a candidate of its own, and it wins over the shared delay with its value."""
    sc = scenario("humanoid", BenchConfig())
    rng = np.random.default_rng(3)
    t, u1 = commands(sc, rng)
    _, u2 = commands(sc, rng)
    truth = {"family": "delay", "effect": "actuator_delay", "joint": "L_Hip_y", "x": [0.04], "x0": [0.01]}
    train, test = (synthesize(sc, truth, t, u, 1.0, rng) for u in (u1, u2))
    res = diagnose([(train, sc.model)], [(test, sc.model)], replace(CFG, families=("delay",)))
    assert res.verdict == "explained" and res.selected["effect"] == "actuator_delay[L_Hip_y]"
    (delay,) = res.selected["parameters"]
    assert delay["ci95"][0] <= 0.04 <= delay["ci95"][1] and abs(delay["value"] - 0.04) < 0.01


def test_two_effects_together_are_found_with_their_shares():
    """Delay and Coulomb friction together: fitted alone, each soaks up part of the other
    (and load friction imitates both); forward selection fits the friction on top of the delay."""
    delay = {"family": "delay", "effect": "actuator_delay", "joint": None, "x": [0.03]}
    coulomb = {"family": "coulomb_friction", "effect": "coulomb_friction", "joint": None, "x": [0.08]}
    sc, train, test = _case({"family": "compound", "parts": [delay, coulomb]}, seed=4)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res.verdict == "explained"
    assert res.selected["family"] == "coulomb_friction+delay"
    values = {p["name"]: p["value"] for p in res.selected["parameters"]}
    assert abs(values["delay"] - 0.03) < 0.005 and abs(values["added"] - 0.08) < 0.015
    shares = {s["effect"].split("[")[0]: s["share"] for s in res.selected["shares"]}
    assert set(shares) == {"actuator_delay", "coulomb_friction"}
    assert sum(shares.values()) == pytest.approx(1.0) and min(shares.values()) > 0.1


def test_a_point_mass_added_to_a_body_moves_it_as_a_welded_body_would():
    """add_point_mass against MuJoCo's own composition: the same mass as a separate body welded
    to the link gives the same accelerations (after the model's constants are recomputed)."""
    xml = """<mujoco><worldbody><body name="a"><joint axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="0.5"/>
      <body name="b" pos="0.3 0 0" quat="0.9 0.1 0.3 0.2"><joint axis="1 0 0"/>
        <geom type="box" size="0.05 0.02 0.03" pos="0.04 0.01 0" mass="0.3"/>{}</body></body></worldbody></mujoco>"""
    point, mass = np.array([0.07, -0.03, 0.05]), 0.4
    inertial = f'<inertial pos="0 0 0" mass="{mass}" diaginertia="1e-9 1e-9 1e-9"/>'
    welded = mujoco.MjModel.from_xml_string(xml.format(f'<body pos="{point[0]} {point[1]} {point[2]}">{inertial}</body>'))
    added = mujoco.MjModel.from_xml_string(xml.format(""))
    fx.add_point_mass(added, added.body("b").id, mass, point)
    mujoco.mj_setConst(added, mujoco.MjData(added))
    qacc = []
    for model in (welded, added):
        data = mujoco.MjData(model)
        data.qpos[:], data.qvel[:] = [0.4, -0.7], [1.0, 2.0]
        mujoco.mj_forward(model, data)
        qacc.append(data.qacc.copy())
    np.testing.assert_allclose(qacc[1], qacc[0], rtol=1e-5)


def test_a_com_shift_moves_a_body_compiled_with_its_com_at_its_origin():
    xml = """<mujoco><worldbody><body><joint axis="0 1 0"/><geom type="sphere" size="0.05" mass="1"{}/></body>
      </worldbody></mujoco>"""
    shifted = mujoco.MjModel.from_xml_string(xml.format(' pos="0.1 0 0"'))
    edited = mujoco.MjModel.from_xml_string(xml.format(""))
    fx.release_inertial_frame(edited, 1)
    edited.body_ipos[1] = [0.1, 0.0, 0.0]
    mujoco.mj_setConst(edited, mujoco.MjData(edited))
    qacc = []
    for model in (shifted, edited):
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        qacc.append(data.qacc[0])
    assert qacc[0] != 0.0 and qacc[1] == pytest.approx(qacc[0], rel=1e-9)


@needs_go2
def test_a_payload_at_the_foot_is_found_with_its_mass():
    sc = scenario("go2", BenchConfig())
    rng = np.random.default_rng(9)
    t, u1 = commands(sc, rng)
    _, u2 = commands(sc, rng)
    truth = {"family": "mass", "effect": "payload", "joint": "FL_calf_joint", "x": [0.4, 0.02, 0.0, -0.18]}
    train, test = (synthesize(sc, truth, t, u, 1.0, rng) for u in (u1, u2))
    res = diagnose([(train, sc.model)], [(test, sc.model)], replace(CFG, families=("mass",)))
    assert res.verdict == "explained" and res.selected["effect"] == "payload[FL_calf_joint]"
    assert abs(_selected_value(res, "mass") - 0.4) < 0.08


@pytest.mark.parametrize("seed", [0, 3])
def test_a_payload_on_a_stamping_leg_is_fitted_through_the_costs_roughness(seed: int) -> None:
    """The rail leg's foot stamps on the floor, so the replay's cost is rugged on fine scales:
    the payload's own millimetre steps stall near its start (offset 0), below the truth's
    fit; steps of 3 % of each range (the default) reach the truth's gap and its offset."""
    sc = scenario("rail_leg", BenchConfig())
    rng = np.random.default_rng(seed)
    t, u = commands(sc, rng)
    x_true = np.array([0.3, 0.15, 0.0, -0.15])  # kg; m along, across the hinge axis, down
    truth = {"family": "mass", "effect": "payload", "joint": "knee", "x": list(x_true)}
    tr = bind(synthesize(sc, truth, t, u, 1.0, rng), sc.model)
    rep = Replayer([tr], make_windows([tr], 0.5))
    combo = Combo((fx.Payload(joints=("knee",)),), tr)
    truth_gap = gap_rms(residuals(rep, [combo.inputs(x_true, [tr])])[0], rep.mask)
    coarse = Fitter(rep).fit(combo)
    fine = Fitter(rep, step_fraction=0.0).fit(combo)
    assert coarse.train_gap <= truth_gap
    assert abs(coarse.x[0] - 0.3) < 0.05 and abs(coarse.x[1] - 0.15) < 0.04
    assert fine.train_gap > 1.2 * truth_gap
    # the offset along the hinge axis changes no torque of the planar leg: no interval for it
    half = Fitter(rep).confidence(combo, coarse.x)
    assert np.isinf(half[2]) and np.isfinite(half[[0, 1, 3]]).all()


def test_bench_draws_two_effects_on_two_joints():
    from crisp_gym.sim2real.bench import draw_truth, nominal_run

    cfg = BenchConfig(p_none=0.0, p_outside=0.0, p_compound=1.0)
    sc = scenario("arm", cfg)
    t, u = commands(sc, np.random.default_rng(0))
    tr = nominal_run(sc, t, u)
    for seed in range(6):
        truth = draw_truth(sc, tr, np.random.default_rng(seed), cfg)
        first, second = truth["parts"]
        assert first["joint"] != second["joint"] and first["family"] != second["family"]
        assert truth["family"] == "+".join(sorted((first["family"], second["family"])))
        assert {first["joint"], second["joint"]} <= set(sc.joints)


@pytest.mark.slow
@needs_go2
def test_different_effects_on_different_joints_are_found_together():
    """Damping on one joint of the Go2 and armature on another: no single family explains
    both; the per-joint mixture (or forward selection) does."""
    sc = scenario("go2", BenchConfig())
    rng = np.random.default_rng(11)
    t, u1 = commands(sc, rng)
    _, u2 = commands(sc, rng)
    parts = [{"family": "viscous_damping", "effect": "viscous_damping", "joint": "FL_thigh_joint", "x": [0.6]},
             {"family": "armature", "effect": "armature", "joint": "RR_calf_joint", "x": [0.02]}]
    truth = {"family": "armature+viscous_damping", "parts": parts}
    train, test = (synthesize(sc, truth, t, u, 1.0, rng) for u in (u1, u2))
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res.verdict == "explained" and res.selected["family"] == "armature+viscous_damping"


def _servo_trajectory(truth: dict, seed: int = 0):
    sc = scenario("servo", BenchConfig())
    rng = np.random.default_rng(seed)
    t, u = commands(sc, rng)
    return sc, bind(synthesize(sc, truth, t, u, 1.0, rng), sc.model)


def test_external_torque_is_the_pendulum_gravity_torque():
    """At rest the servo's load is its pendulum's gravity torque, -m g l sin(q)."""
    sc, tr = _servo_trajectory({"family": "none"})
    m = sc.model
    body = m.jnt_bodyid[0]
    lever = np.linalg.norm(m.body_ipos[body] - m.jnt_pos[0])
    q = np.linspace(-1.5, 1.5, 7)[:, None]
    tau = fx.external_torque(m, tr, np.array([0]), q, np.zeros_like(q))[:, 0]
    weight = m.body_subtreemass[body] * -m.opt.gravity[2]
    np.testing.assert_allclose(tau, -weight * lever * np.sin(q[:, 0]), atol=1e-9)


def test_gearbox_friction_without_its_directional_and_rest_terms_is_load_friction():
    sc, tr = _servo_trajectory({"family": "none"})
    idx = np.arange(0, len(tr.log.time), 7)
    args = (tr, sc.model, tr.ctrl[idx * tr.nsub], tr.enabled[idx], tr.log.qpos[idx], tr.qvel[idx])
    plain = fx.LoadFriction().friction(np.array([0.3]), *args)
    gearbox = fx.GearboxFriction().friction(np.array([0.3, 0.0, 0.0, 1.0]), *args)
    np.testing.assert_allclose(gearbox, plain, rtol=1e-12)
    assert plain.max() > 0.01  # the log loads the gear train


def test_gearbox_friction_fits_back():
    """A directional gear friction that sticks harder at rest: the fit finds the load
    coefficients it was made with, and load friction alone cannot reproduce it."""
    truth = {"family": "load_friction", "effect": "gearbox_friction", "joint": None, "x": [0.25, 0.12, 1.0, 0.5],
             "x0": [0.0, 0.0, 0.0, 0.5]}
    sc, tr = _servo_trajectory(truth, seed=10)
    fitter = Fitter(Replayer([tr], make_windows([tr], 0.5)))
    full = fitter.fit(Combo((fx.GearboxFriction(),), tr))
    plain = fitter.fit(Combo((fx.LoadFriction(),), tr))
    assert abs(full.x[0] - 0.25) < 0.05 and abs(full.x[1] - 0.12) < 0.05
    assert full.train_gap < 0.5 * plain.train_gap


# ----------------------------------------------------------------------------- gear play


def _hold(sc, u: float, truth: dict, seconds: float = 3.0) -> float:
    """Where the servo's pendulum comes to rest under a constant command ``u``."""
    t = np.arange(int(seconds * sc.rate)) / sc.rate
    return float(synthesize(sc, truth, t, np.full((len(t), 1), u), 0.0, np.random.default_rng(0)).qpos[-1, 0])


def _open_loop(sc, u: float, effect: fx.Effect, x: float, seconds: float = 3.0) -> float:
    """Where the library's model with ``effect`` at ``x`` comes to rest under a constant command ``u``."""
    from crisp_gym.sim2real.bench import _template

    t = np.arange(int(seconds * sc.rate)) / sc.rate
    tr = replace(_template(sc, t, np.full((len(t), 1), u)), spec=sc.spec())
    inputs = Combo((effect,), tr).inputs(np.array([x]), [tr])
    return float(Replayer([tr], make_windows([tr], 1.0)).open_loop_states(inputs)[0][0][-1, 0])


@pytest.mark.parametrize("u", [0.8, -0.8])
def test_gear_play_rests_a_half_width_short_on_the_load_side(u: float) -> None:
    """Gravity holds the gear on one side: the joint rests where the nominal servo rests for a
    command ``half_width`` closer to hanging (give or take the gap's stiff but compliant end), in
    the library's model as in the bench's own gear. The play operator on the command does not
    move the rest at all."""
    sc = scenario("servo", BenchConfig())
    g = 0.03
    nominal = {"family": "none"}
    shifted = _hold(sc, u - np.sign(u) * g, nominal)
    assert abs(_hold(sc, u, nominal) - shifted) > 0.5 * g  # the known answer is not the nominal one
    library = _open_loop(sc, u, fx.GearPlay(), g)
    assert library == pytest.approx(shifted, abs=0.2 * g)
    bench = _hold(sc, u, {"family": "backlash", "effect": "gear_play", "joint": None, "x": [g], "x0": [0.01]})
    assert library == pytest.approx(bench, abs=0.02 * g)
    assert _open_loop(sc, u, fx.Backlash(), g) == pytest.approx(_hold(sc, u, nominal), abs=1e-9)


def _arm_log(truth: dict | None, seed: int = 1) -> tuple:
    """The arm's scenario and a noisy log of ``truth`` (None: the nominal model), bound with its spec."""
    sc = scenario("arm", BenchConfig())
    rng = np.random.default_rng(seed)
    t, u = commands(sc, rng)
    return sc, bind(synthesize(sc, truth or {"family": "none"}, t, u, 1.0, rng), sc.spec())


def test_models_of_two_state_layouts_replay_in_one_call_as_apart() -> None:
    """A candidate with a rotor (more state than the log's model) and a plain one, simulated
    together, predict exactly what each predicts alone; the rotor's gap closed (half-width 0)
    replays nearly as the nominal model, whose joint carries the rotor's inertia rigidly."""
    sc, tr = _arm_log(None)
    rep = Replayer([tr], make_windows([tr], 0.3))
    plain = Combo((), tr).inputs(np.zeros(0), [tr])
    gear = Combo((fx.GearPlay(),), tr)
    closed, wide = gear.inputs(np.array([0.0]), [tr]), gear.inputs(np.array([0.02]), [tr])
    assert closed.models[0].nq == tr.model.nq + len(sc.actuators)
    together = rep.simulate([plain, wide, closed])
    for k, inp in enumerate((plain, wide, closed)):
        np.testing.assert_array_equal(together[k], rep.simulate([inp])[0])
    off_nominal = [float(np.sqrt(np.mean((q - together[0])[rep.mask] ** 2))) for q in together[1:]]
    assert off_nominal[1] < 0.05 * off_nominal[0]


def test_gear_play_needs_the_models_spec() -> None:
    """Given the compiled model only, gear play cannot add its rotor and says why (the
    diagnosis then skips it with that reason)."""
    _, tr = _arm_log(None)
    with pytest.raises(fx.CannotApply, match="MjSpec"):
        Combo((fx.GearPlay(),), replace(tr, spec=None)).inputs(np.array([0.01]), [replace(tr, spec=None)])


def _rail_leg_template():
    from crisp_gym.sim2real.bench import _template

    sc = scenario("rail_leg", BenchConfig())
    t, u = commands(sc, np.random.default_rng(0))
    return _template(sc, t, u)


def test_actuator_effects_leave_out_the_joints_no_actuator_drives() -> None:
    """The rail leg's slide is logged but not driven. Effects that act through the actuators
    (gains, limits, delays, play) get no candidate confined to it (a gear-play screen confined
    to it once crashed the diagnosis) and, per joint, no parameter for it (one there took a
    meaningless value and counted in the parameter penalty); joint effects keep it."""
    tr = _rail_leg_template()
    library = fx.library(tr, focus="rail")
    labels = [e.label for e in library]
    assert "gear_play[shared]" in labels and "coulomb_friction[rail]" in labels
    on_drives = [k for k in fx.EFFECT_TYPES if k.on_drives]
    assert {k.name for k in on_drives} >= {"pd_gain_scale", "torque_saturation", "actuator_delay", "backlash"}
    assert not [e for e in library if e.on_drives and e.joints == ("rail",)]
    params = {e.label: [p.name for p in e.params(tr)] for e in library if e.per_joint}
    assert params["pd_gain_scale[per-joint]"] == ["scale@hip", "scale@knee"]
    assert params["actuator_delay[per-joint]"] == ["delay@hip", "delay@knee"]
    assert params["viscous_damping[per-joint]"] == ["added@rail", "added@hip", "added@knee"]


def test_a_combination_keeps_only_parts_the_fitted_windows_see() -> None:
    """On an arm log with a PD gain error on one joint and added damping on another, leaving
    out either part at its true value raises the squared gap by more than noise alone moves it
    (the noise draws' spread); on a log with the gain error alone, the same pair with damping
    held near none does not, and neither does a pair whose second part (an encoder bias of a
    tenth of the noise) changes nothing."""
    from crisp_gym.sim2real.bench import driven_joints

    gain_joint, damped_joint = driven_joints(scenario("arm", BenchConfig()))[1:3]
    gain = {"family": "pd_gain", "effect": "pd_gain_scale", "joint": gain_joint, "x": [1.6], "x0": [1.0]}
    damping = {"family": "viscous_damping", "effect": "viscous_damping", "joint": damped_joint, "x": [1.0],
               "x0": [0.0]}
    pair = (fx.GainScale(joints=(gain_joint,)), fx.ViscousDamping(joints=(damped_joint,)))
    for truth, x, supported in (({"family": "compound", "effect": "compound", "parts": [gain, damping]},
                                 [1.6, 1.0], True),
                                (gain, [1.6, 0.005], False)):
        sc, tr = _arm_log(truth)
        rep = Replayer([tr], make_windows([tr], 0.3))
        spread = noise_spread(noise_floors(rep, 0))
        candidate = Candidate(Combo(pair, tr), np.array(x), 0.0)
        skipped: list[dict[str, str]] = []
        assert _supported([candidate], rep, spread, skipped) == ([candidate] if supported else [])
        assert [s["effect"] for s in skipped] == ([] if supported else [candidate.combo.label])
    bias = Candidate(Combo((pair[0], fx.EncoderBias(joints=(damped_joint,))), tr),
                     np.array([1.6, 0.1 * sc.sigma]), 0.0)
    skipped = []
    assert _supported([bias], rep, spread, skipped) == []
    assert skipped[0]["reason"].startswith(f"encoder_bias[{damped_joint}] does not earn its place")


def test_at_equal_parameter_counts_one_effect_is_simpler_than_a_mixture() -> None:
    """A per-joint mixture (damping on the rail, gains on the hip and knee: three parameters in
    two effects) and one effect on every joint (damping per joint: three in one) whose held-out
    gaps differ by less than the noise: parsimony puts the single effect first, as it would
    one with fewer parameters; beyond the noise the mixture keeps its place."""
    tr = _rail_leg_template()
    mixture = Candidate(Combo((fx.ViscousDamping(joints=("rail",), per_joint=True),
                               fx.GainScale(joints=("hip", "knee"), per_joint=True)), tr), np.ones(3), 0.0,
                        heldout_gap=1.00, score=1.0)
    single = Candidate(Combo((fx.ViscousDamping(per_joint=True),), tr), np.ones(3), 0.0, heldout_gap=1.05, score=1.1)
    assert mixture.nparam == single.nparam == 3
    assert _parsimonious_first([mixture, single], floor=0.5, tolerance=1.0)[0] is single
    assert _parsimonious_first([mixture, single], floor=0.1, tolerance=1.0)[0] is mixture


def test_a_links_mass_is_also_tried_on_each_body_below_the_focus_joint() -> None:
    """A light tool shows most at the joints that carry it, so the gap's focus may be a joint
    above the link whose mass is off. Mass scale is tried confined to the focus and to each
    body below it: on the arm's chain every later joint; on the humanoid one joint per body
    of the leg (its three hinges move the same bodies), never a body of the other leg."""
    from crisp_gym.sim2real.bench import _template

    def template(name: str):
        sc = scenario(name, BenchConfig())
        return _template(sc, *commands(sc, np.random.default_rng(0)))

    arm = template("arm")
    assert fx.joints_below(arm, "arm2") == ["arm3", "arm4", "arm5", "arm6"]
    assert fx.joints_below(arm, "arm6") == []
    labels = [e.label for e in fx.library(arm, focus="arm4")]
    assert {"mass_scale[arm4]", "mass_scale[arm5]", "mass_scale[arm6]"} <= set(labels)
    assert "mass_scale[arm3]" not in labels and "com_shift[arm6]" not in labels
    assert fx.joints_below(template("humanoid"), "R_Hip_x") == ["R_Knee_x", "R_Ankle_x", "R_Toe_x"]


def test_per_joint_mixture_gives_each_joint_the_best_effect_with_a_parameter_there() -> None:
    """Gains per joint win the hip, damping the knee; the rail, where the gain has no
    parameter, goes to damping even though the gain's fit left the rail's gap smaller. The
    mixture starts from each winner's fitted values on its joints."""
    tr = _rail_leg_template()
    gain = Candidate(Combo((fx.GainScale(per_joint=True),), tr), np.array([1.3, 0.7]), 0.0,
                     heldout_per_joint=np.array([0.1, 0.1, 0.3]))
    damping = Candidate(Combo((fx.ViscousDamping(per_joint=True),), tr), np.array([2.0, 3.0, 4.0]), 0.0,
                        heldout_per_joint=np.array([0.2, 0.4, 0.2]))
    seen = []

    class Recorder:  # a fitter that returns its start, so that the mixture's composition shows
        def fit(self, combo, starts):
            seen.append((combo, starts))
            return SimpleNamespace(x=starts[0], train_gap=0.0)

    mixture = _per_joint_mixture([gain, damping], tr, Recorder())
    assert [e.label for e in mixture.combo.effects] == ["pd_gain_scale[per-joint: hip]",
                                                         "viscous_damping[per-joint: rail,knee]"]
    np.testing.assert_array_equal(seen[0][1][0], [1.3, 2.0, 4.0])
    assert _per_joint_mixture([gain], tr, Recorder()) is None


def test_candidates_the_noise_cannot_tell_from_the_winner_are_named_simplest_first() -> None:
    """Floor 0.01, tolerance 1: a squared held-out gap within 1e-4 of the smallest (0.0095²,
    i.e. up to 0.0138) cannot be told from it. The support box (0.0120) and the tilt (0.0130)
    are named, the tilt first (two parameters against three); the mass (0.0145) is not. The
    ground height's richer relative, and the support box's, are the same model with a part it
    does not need; the winner's own family is the winner."""
    tr = _rail_leg_template()

    def cand(effects, gap):
        combo = Combo(tuple(effects), tr)
        return Candidate(combo, np.zeros(len(combo.params)), 0.0, heldout_gap=gap, score=gap**2)

    ranked = [cand([fx.GroundHeight()], 0.0100),
              cand([fx.GroundHeight(), fx.MassScale()], 0.0095),  # richer than the winner
              cand([fx.SupportBox()], 0.0120),
              cand([fx.SupportBox(), fx.ViscousDamping()], 0.0118),  # richer than a named one
              cand([fx.GroundTilt()], 0.0130),
              cand([fx.MassScale()], 0.0145)]
    named = _indistinguishable(ranked, floor=0.01, tolerance=1.0)
    assert [c.combo.family for c in named] == ["ground_tilt", "support_box"]
    assert _indistinguishable(ranked, floor=0.001, tolerance=1.0) == []  # a low floor tells them all apart


def test_bench_credits_a_truth_named_indistinguishable_apart_from_the_winner():
    """A support box called ground height, with the box named as indistinguishable: a miss,
    and right when the diagnosis's alternatives count; an unexplained verdict names nothing."""
    from crisp_gym.sim2real.bench import score_case

    truth = {"family": "support_box", "effect": "support_box", "x": [0.02, 0.0, 0.0], "x0": [0.0, 0.0, 0.0],
             "signature": 0.1}
    selected = {"family": "ground_height", "parameters": [],
                "indistinguishable": [{"effect": "support_box[shared]", "family": "support_box", "gap_heldout": 0.01}]}
    explained = SimpleNamespace(verdict="explained", selected=selected, noise_floor=0.01, shrink=0.9,
                                gap_before=0.1, where={"worst_joint": "hip"})
    row = score_case(truth, explained)
    assert not row["correct"] and row["correct_or_indistinguishable"] and row["indistinguishable"] == 1
    row = score_case(truth, SimpleNamespace(**{**vars(explained), "verdict": "unexplained", "selected": None}))
    assert not row["correct"] and not row["correct_or_indistinguishable"] and row["indistinguishable"] == 0


@pytest.mark.parametrize("timestep", [1 / 120, 1 / 500])
def test_a_gap_end_yields_by_its_compliance_times_the_force_it_holds(timestep: float) -> None:
    """A rotor pushed into its gap's end by a constant motor torque, the joint held by a spring:
    MuJoCo's own simulation, once at rest, has the end pressed in by limit_compliance x the
    torque, for pressings deeper than the limit's impedance width (1 mm), at a 120 Hz step
    (where it rivals the gap) and at 500 Hz (where it is ten times smaller)."""
    for torque in (3.0, 4.5):
        spec = mujoco.MjSpec()
        spec.option.timestep = timestep
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
        link = spec.worldbody.add_body(name="link", mass=1.0, inertia=[0.1] * 3, explicitinertial=True)
        link.add_joint(name="j", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1], stiffness=200.0, damping=5.0)
        spec.add_actuator(name="motor", target="j", trntype=mujoco.mjtTrn.mjTRN_JOINT)
        fx.add_rotors(spec, ["j"], [0.002], timestep)
        model = spec.compile()
        data = mujoco.MjData(model)
        data.ctrl[0] = torque
        mujoco.mj_step(model, data, nstep=int(3.0 / timestep))
        assert np.abs(data.qvel).max() < 1e-6  # at rest
        tendon = model.tendon("j_play").id
        depth = data.ten_length[tendon] - model.tendon_range[tendon, 1]
        assert depth > model.tendon_solimp_lim[tendon, 2]
        assert depth == pytest.approx(fx.limit_compliance(model, np.array([tendon]))[0] * torque, rel=1e-6)


def test_rotor_track_follows_the_simulated_rotor_closer_than_its_force_balance() -> None:
    """A noise-free log of the library's own gear model (arm, 0.02 rad gaps on every drive), its
    rotors' true places in their gaps kept: rotor_track, which sees only the log, finds them to
    within a quarter of the error of the quasi-static guess (the drive's force balance, clipped
    to the gap) that windows started from before (measured: 0.0013 against 0.0118 rad)."""
    from mujoco import rollout

    from crisp_gym.sim2real.effects.gear_play import rotor_track

    sc, tr = _arm_log(None)
    effect, b = fx.GearPlay(), 0.02
    inputs = Combo((effect,), tr).inputs(np.array([b]), [tr])
    model = inputs.models[0]
    first = Replayer([tr], make_windows([tr], 0.3))._start_states(inputs, 0, np.array([0]))
    states, _ = rollout.rollout(model, mujoco.MjData(model), first, inputs.ctrl[0][None])
    full = np.concatenate([first, states[0, tr.nsub - 1::tr.nsub]])[:len(tr.log.time)]
    rotors = effect._build(tr)[2]
    exact = replace(bind(replace(tr.log, qpos=full[:, 1 + tr.qadr]), sc.spec(), validate=False),
                    qvel=full[:, 1 + model.nq + tr.dadr])
    q = exact.log.qpos[:, rotors.cols]
    truth = full[:, 1 + rotors.qadr] - q
    offset, _ = rotor_track(b, exact, model, inputs.ctrl[0], rotors.cols, rotors.dadr, rotors.actuators,
                            fx.limit_compliance(model, rotors.tendons))
    drives = np.concatenate(rotors.actuators)  # one position servo per joint on the arm
    gain, stiffness = model.actuator_gainprm[drives, 0], -model.actuator_biasprm[drives, 1]
    target = inputs.ctrl[0][::tr.nsub][:, drives] * gain / stiffness
    guess = np.clip(target - q, -b, b)
    moving = np.abs(truth).max(axis=0) > 0.5 * b  # drives whose rotor does cross its gap
    assert moving.any()
    err_track = np.sqrt(np.mean((offset - truth)[:, moving] ** 2))
    err_guess = np.sqrt(np.mean((guess - truth)[:, moving] ** 2))
    assert err_track < 0.25 * err_guess


def test_gear_play_is_fitted_back_from_a_real_gap() -> None:
    """On the arm, a log made with the bench's own rotor and real gap in one joint's gear
    train: the library's gear play finds the gap's half-width and explains the log far better
    than the play operator on the command or Coulomb friction."""
    from crisp_gym.sim2real.bench import driven_joints

    joint = driven_joints(scenario("arm", BenchConfig()))[1]
    sc, tr = _arm_log({"family": "backlash", "effect": "gear_play", "joint": joint, "x": [0.02], "x0": [0.01]})
    fitter = Fitter(Replayer([tr], make_windows([tr], 0.3)))
    gear = fitter.fit(Combo((fx.GearPlay(joints=(joint,)),), tr))
    assert gear.x[0] == pytest.approx(0.02, rel=0.05)
    for other in (fx.Backlash(joints=(joint,)), fx.CoulombFriction(joints=(joint,))):
        assert gear.train_gap < 0.3 * fitter.fit(Combo((other,), tr)).train_gap


def test_mujoco_warnings_are_counted_not_printed_or_logged(tmp_path, monkeypatch, capfd) -> None:
    """A replay that blows up inside ``collected_warnings`` is counted by message, nothing is
    printed or written to MUJOCO_LOG.TXT, and the previous handler is back afterwards."""
    from mujoco import rollout

    from crisp_gym.sim2real.replay import collected_warnings

    monkeypatch.chdir(tmp_path)
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><option timestep="0.01"/><worldbody><body><joint name="j"/><geom size=".1" mass="1e-6"/>'
        '</body></worldbody><actuator><position joint="j" kp="1e9"/></actuator></mujoco>')
    state = np.zeros((8, mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)))
    previous = mujoco.get_mju_user_warning()
    with collected_warnings() as counts:
        rollout.rollout([model] * 8, [mujoco.MjData(model) for _ in range(2)], state, np.ones((8, 50, 1)))
    assert sum(counts.values()) >= 8
    assert all("N" in message and not any(ch.isdigit() for ch in message) for message in counts)
    assert mujoco.get_mju_user_warning() is previous
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    printed = capfd.readouterr()
    assert "unstable" not in printed.out + printed.err


def test_a_sweep_held_out_at_its_end_is_flagged_as_faster_and_blocks_spread_it():
    # a frequency sweep from 0.5 to 2 Hz: its last 30 % moves about twice as fast as the rest
    t = np.arange(0, 20, 0.005)
    phase = 2 * np.pi * (0.5 * t + 1.5 * t**2 / 40)
    sweep = RealLog(time=t, qpos=0.3 * np.sin(phase)[:, None], ctrl=0.3 * np.sin(phase)[:, None],
                    joint_names=("hinge",), actuator_names=("servo",))
    fitted, held = sweep.holdout_blocks(0.3)
    assert speed_ratio(fitted, held) > 1.5
    fitted, held = sweep.holdout_blocks(0.3, blocks=8)
    assert abs(speed_ratio(fitted, held) - 1.0) < 0.15
    at_end = SimpleNamespace(heldout_speed_ratio=1.8, heldout="the last 30 % of every log",
                             config={"holdout_blocks": 1})
    assert "1.8 times as fast" in extrapolation_lines(at_end)[0] and "holdout-blocks" in extrapolation_lines(at_end)[0]
    logs = SimpleNamespace(heldout_speed_ratio=0.5, heldout="held-out logs", config={"holdout_blocks": 1})
    assert "0.5 times as fast" in extrapolation_lines(logs)[0] and "holdout-blocks" not in extrapolation_lines(logs)[0]
    assert extrapolation_lines(SimpleNamespace(heldout_speed_ratio=1.1, heldout="held-out logs", config={})) == []


def test_held_out_blocks_of_one_log_find_its_delay():
    truth = {"family": "delay", "effect": "actuator_delay", "joint": None, "x": [0.03], "x0": [0.01]}
    sc, train, _ = _case(truth)
    res = diagnose([(train, sc.model)], None, replace(CFG, holdout_blocks=3))
    assert res.heldout == "the last 30 % of each of 3 equal parts of every log"
    assert res.verdict == "explained" and abs(res.selected["parameters"][0]["value"] - 0.03) < 0.003
    assert 0.67 < res.heldout_speed_ratio < 1.5  # the bench's commands do not change over the log


def test_blockwise_derivatives_are_the_per_joint_diagonal_beside_full_columns() -> None:
    """With ``blockwise`` (forward selection's screen), a per-joint effect beside a shared one
    gets the derivatives it gets alone (one perturbed rollout, each parameter on its own joint,
    the shared effect held where it is), and the shared effect its full column, as without."""
    sc = scenario("arm", BenchConfig())
    rng = np.random.default_rng(0)
    t, u = commands(sc, rng)
    tr = bind(synthesize(sc, {"family": "none"}, t, u, 1.0, rng), sc.model)
    rep = Replayer([tr], make_windows([tr], 0.5))
    damping, friction = fx.ViscousDamping(per_joint=True), fx.CoulombFriction()
    combo = Combo((damping, friction), tr)
    n = len(tr.log.joint_names)
    x = np.concatenate([np.full(n, 0.3), [0.1]]) * np.array([p.hi for p in combo.params])
    hi = np.array([p.hi for p in combo.params])
    step = 0.03 * hi
    r = residuals(rep, [combo.inputs(x, [tr])])[0]
    blockwise, full = Fitter(rep, blockwise=True), Fitter(rep)
    jac = blockwise._jacobian(combo, x, r, None, step, hi)
    assert blockwise.rollouts == 2 * len(rep.windows)
    np.testing.assert_array_equal(jac[n], full._jacobian(combo, x, r, None, step, hi)[n])
    alone = Combo((damping, Frozen(friction, x[n:])), tr)
    diagonal = full._jacobian(alone, x[:n], r, np.arange(n), step[:n], hi[:n])  # (nwin, size-1, n)
    for j in range(n):
        np.testing.assert_array_equal(jac[j, ..., j], diagonal[..., j])
        assert not np.delete(jac[j], j, axis=-1).any()


def test_noise_floor_draws_are_ordered_and_the_median_one_is_the_reported_floor() -> None:
    """The diagnosis reports the median of its noise draws as the nominal model's floor; the
    draws come ordered by their overall RMS, so the last one is the largest gap the exact
    model produced."""
    sc, train, test = _case({"family": "none"}, seed=4)
    tr = [bind(test, sc.model)]
    rep = Replayer(tr, make_windows(tr, CFG.window_s))
    floors = noise_floors(rep, CFG.seed, draws=CFG.floor_draws)
    overall = np.sqrt(np.mean(floors**2, axis=1))
    assert floors.shape == (CFG.floor_draws, 1) and np.all(np.diff(overall) >= 0)
    np.testing.assert_array_equal(median_draw(floors), floors[2])
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res.noise_floor == pytest.approx(overall[2], rel=1e-12)


def test_independent_chains_share_a_perturbed_rollout_and_keep_every_derivative() -> None:
    """The bench humanoid's legs hang from a fixed pelvis: a per-joint effect's derivatives on
    the left leg and on the right one come from the same rollouts (12 for 24 parameters, plus
    one for a shared effect), each read on its own leg's columns, and equal the derivatives of
    one parameter perturbed at a time, cross-joint terms included."""
    sc = scenario("humanoid", BenchConfig())
    rng = np.random.default_rng(0)
    t, u = commands(sc, rng)
    tr = bind(synthesize(sc, {"family": "none"}, t, u, 1.0, rng), sc.model)
    rep = Replayer([tr], make_windows([tr], 0.5))
    assert sorted(np.unique(chains(tr), return_counts=True)[1]) == [12, 12]
    combo = Combo((fx.ViscousDamping(per_joint=True), fx.CoulombFriction()), tr)
    hi = np.array([p.hi for p in combo.params])
    x, step = 0.2 * hi, 0.03 * hi
    r = residuals(rep, [combo.inputs(x, [tr])])[0]
    fitter = Fitter(rep)
    jac = fitter._jacobian(combo, x, r, None, step, hi)
    assert fitter.rollouts == 13 * len(rep.windows)
    one_at_a_time = residuals(rep, [combo.inputs(x + step * (np.arange(len(x)) == i), [tr]) for i in range(len(x))])
    expected = (one_at_a_time - r) / step[:, None, None, None]
    assert np.abs(expected[0, ..., 1:12]).max() > 0.1 * np.abs(expected[0, ..., 0]).max()  # the hip moves the knee
    assert np.abs(expected[:12, ..., 12:]).max() < 1e-9 * np.abs(expected).max()  # the left leg moves not the right
    np.testing.assert_allclose(jac, expected, rtol=0, atol=1e-6 * np.abs(expected).max())


def test_a_richer_form_above_the_last_base_is_a_base_of_its_own() -> None:
    """Forward selection's bases are the best singles of distinct families; gearbox friction
    shares load friction's family, so where it ranks second (behind load friction on every
    joint, ahead of the next family) only the extra rule makes it a base. Below the last base,
    or as the best single itself, it is not added twice or at all."""
    def single(effect: type, label: str):
        return SimpleNamespace(combo=SimpleNamespace(family=effect.family, label=label, effects=(effect(),)))

    load, gearbox = single(fx.LoadFriction, "load[per-joint]"), single(fx.GearboxFriction, "gearbox[thigh]")
    gain, delay = single(fx.GainScale, "gain[per-joint]"), single(fx.ActuatorDelay, "delay[thigh]")
    assert forward_bases([load, gearbox, gain, delay], 2) == [load, gain, gearbox]
    assert forward_bases([load, gain, gearbox, delay], 2) == [load, gain]  # below the last base
    assert forward_bases([gearbox, load, gain, delay], 2) == [gearbox, gain]  # a base by the first rule
    assert forward_bases([load, gearbox], 2) == [load]  # one family: the richer form is above no other base
    assert forward_bases([], 2) == []
