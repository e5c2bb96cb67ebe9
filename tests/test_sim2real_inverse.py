"""The joint model estimated from inverse dynamics (crisp_gym.sim2real.inverse) and its fit in the diagnosis."""

import numpy as np
import pytest

from crisp_gym.sim2real import effects as fx
from crisp_gym.sim2real.bench import BenchConfig, commands, nominal_run, scenario, synthesize
from crisp_gym.sim2real.diagnose import DiagnoseConfig, _joint_model_fit, diagnose
from crisp_gym.sim2real.effects import CannotApply
from crisp_gym.sim2real.fit import Fitter
from crisp_gym.sim2real.inverse import JOINT_MODEL, estimate_joint_model, joint_model_start
from crisp_gym.sim2real.replay import Replayer, bind, make_windows

ARM_TRUTH = {"family": "compound", "effect": "compound", "parts": [
    {"family": "coulomb_friction", "effect": "coulomb_friction", "joint": "arm2", "x": [2.5]},
    {"family": "viscous_damping", "effect": "viscous_damping", "joint": "arm3", "x": [2.0]},
    {"family": "armature", "effect": "armature", "joint": "arm5", "x": [0.003]},
]}


def _arm_log(noise: float, seed: int = 0):
    sc = scenario("arm", BenchConfig())
    rng = np.random.default_rng(seed)
    t, u = commands(sc, rng)
    return sc, synthesize(sc, ARM_TRUTH, t, u, noise, rng)


def test_the_regression_recovers_each_joints_own_friction_damping_and_armature():
    """A different effect on each of three arm joints, whose drives span 100x, from a noisy
    log: every joint's estimate is the model's value plus what was hidden there (within 20 %),
    and close to nothing where nothing was hidden (against each joint's own scales; the armature
    within 15 % of the joint's inertia, which smoothing the accelerations biases)."""
    sc, log = _arm_log(noise=1.0)
    tr = bind(log, sc.model)
    est = estimate_joint_model([tr])
    torque, speed, inertia = fx.torque_scale(tr), fx.speed_scale(tr), fx.inertia_scale(tr)
    hidden = {(p["effect"], p["joint"]): p["x"][0] for p in ARM_TRUTH["parts"]}
    for j, name in enumerate(sc.joints):
        truth = [hidden.get(("coulomb_friction", name)), hidden.get(("viscous_damping", name)),
                 hidden.get(("armature", name))]
        scales = [torque[j], torque[j] / speed[j], inertia[j]]
        for k, (x, scale, tol) in enumerate(zip(truth, scales, (0.05, 0.05, 0.15))):
            if x is None:
                assert abs(est[j, k]) < tol * scale, (name, k, est[j])
            else:
                assert est[j, k] == pytest.approx(x, rel=0.2), (name, k, est[j])
        assert est[j, 3] < 0.05, (name, est[j])  # no load-dependent friction was hidden


def test_the_start_is_the_estimate_less_the_model_within_bounds():
    sc, log = _arm_log(noise=0.0)
    tr = bind(log, sc.model)
    effects = tuple(kind(per_joint=True) for kind in JOINT_MODEL)
    x = joint_model_start([tr], effects)
    est = estimate_joint_model([tr])
    n = len(sc.joints)
    assert x.shape == (4 * n,)
    j = list(sc.joints).index("arm3")
    assert x[n + j] == pytest.approx(est[j, 1] - sc.model.dof_damping[tr.dadr[j]])
    params = [p for e in effects for p in e.params(tr)]
    assert np.all(x >= [p.lo for p in params]) and np.all(x <= [p.hi for p in params])


def test_a_model_with_degrees_of_freedom_the_log_lacks_cannot_be_regressed():
    sc = scenario("humanoid", BenchConfig())  # its trunk and arms are not in the log
    rng = np.random.default_rng(0)
    t, u = commands(sc, rng)
    tr = nominal_run(sc, t, u)
    with pytest.raises(CannotApply, match="degrees of freedom"):
        estimate_joint_model([tr])
    fitter = Fitter(Replayer([tr], make_windows([tr], 0.5), 2))
    skipped: list[dict[str, str]] = []
    assert _joint_model_fit([tr], fitter, DiagnoseConfig(show_progress=False), skipped) is None
    assert "degrees of freedom" in skipped[0]["reason"]
    skipped.clear()
    restricted = DiagnoseConfig(show_progress=False, families=("coulomb_friction",))
    assert _joint_model_fit([tr], fitter, restricted, skipped) is None and not skipped  # as the singles are


def test_the_diagnosis_fits_the_joint_model_and_prunes_it_to_the_effects_the_log_holds():
    """Coulomb friction and damping together on the servo: fitted by replay from the regression,
    the joint model finds both values and leaves the held-out gap at the noise floor; its
    armature and load friction, which the log does not need, are pruned. Without the option it
    is not fitted."""
    sc = scenario("servo", BenchConfig())
    truth = {"family": "compound", "effect": "compound", "parts": [
        {"family": "coulomb_friction", "effect": "coulomb_friction", "joint": None, "x": [0.06]},
        {"family": "viscous_damping", "effect": "viscous_damping", "joint": None, "x": [0.02]}]}
    rng = np.random.default_rng(3)
    t, u1 = commands(sc, rng)
    _, u2 = commands(sc, rng)
    train, test = synthesize(sc, truth, t, u1, 1.0, rng), synthesize(sc, truth, t, u2, 1.0, rng)
    res = diagnose([(train, sc.model)], [(test, sc.model)], DiagnoseConfig(show_progress=False))
    joint_models = [r for r in res.ranking if "[per-joint]" in r["effect"]]
    assert [r["effect"] for r in joint_models] == ["coulomb_friction[per-joint] + viscous_damping[per-joint]"]
    row = joint_models[0]
    assert row["gap_heldout"] < 1.6 * res.noise_floor < 0.5 * res.gap_before
    params = row["parameters"]  # named by effect where names repeat
    joint = sc.joints[0]
    assert params[f"coulomb_friction.added@{joint}"] == pytest.approx(0.06, rel=0.1)
    assert params[f"viscous_damping.added@{joint}"] == pytest.approx(0.02, rel=0.1)
    plain = diagnose([(train, sc.model)], [(test, sc.model)], DiagnoseConfig(show_progress=False,
                                                                               inverse_dynamics=False))
    assert not any("[per-joint]" in r["effect"] for r in plain.ranking)
