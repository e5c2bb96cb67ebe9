"""Identification on logs generated with a known effect (the servo pendulum: fast)."""

import json

import numpy as np
import pytest

from crisp_gym.sim2real import effects as fx
from crisp_gym.sim2real.bench import commands, scenario, synthesize, BenchConfig
from crisp_gym.sim2real.diagnose import DiagnoseConfig, diagnose
from crisp_gym.sim2real.fit import Combo, Fitter
from crisp_gym.sim2real.replay import Replayer, bind, make_windows
from crisp_gym.sim2real.report import REPORT_KEYS, write_report

CFG = DiagnoseConfig(show_progress=False)


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
    assert res["verdict"] == "explained" and res["selected"]["family"] == "delay"
    p = res["selected"]["parameters"][0]
    assert abs(p["value"] - 0.03) < 0.003
    assert res["shrink"] > 0.8


def test_no_effect_gives_none():
    sc, train, test = _case({"family": "none"}, seed=1)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res["verdict"] == "none"


def test_friction_value_and_interval():
    sc, train, test = _case({"family": "coulomb_friction", "effect": "coulomb_friction", "joint": None,
                             "x": [0.08], "x0": [0.0]}, seed=2)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res["selected"]["family"] == "coulomb_friction"
    lo, hi = res["selected"]["parameters"][0]["ci95"]
    assert abs(res["selected"]["parameters"][0]["value"] - 0.08) < 0.008 and lo <= 0.08 <= hi


def test_outside_effect_is_unexplained():
    sc, train, test = _case({"family": "outside", "kind": "command_filter", "tau": 0.05}, seed=3)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    assert res["verdict"] == "unexplained"


@pytest.mark.parametrize("kind, x", [(fx.GainScale, 0.6), (fx.MassScale, 1.8), (fx.EncoderBias, 0.05)])
def test_each_effect_fits_back(kind, x):
    sc = scenario("servo", BenchConfig())
    truth = {"family": kind.family, "effect": kind.name, "joint": None, "x": [x], "x0": [0.0]}
    _, train, _ = _case(truth, seed=4)
    tr = bind(train, sc.model)
    fitter = Fitter(Replayer([tr], make_windows([tr], 0.5)))
    res = fitter.fit(Combo((kind(),), tr))
    assert abs(res.x[0] - x) < 0.02 * max(1.0, abs(x))


def test_report_files(tmp_path):
    truth = {"family": "delay", "effect": "actuator_delay", "joint": None, "x": [0.02], "x0": [0.01]}
    sc, train, test = _case(truth, seed=5)
    res = diagnose([(train, sc.model)], [(test, sc.model)], CFG)
    out = write_report(res, tmp_path / "rep")
    data = json.loads((out / "report.json").read_text())
    assert all(k in data for k in REPORT_KEYS)
    assert (out / "report.md").read_text().startswith("# Sim-to-real gap diagnosis")
    assert (out / "overlay.png").is_file() and (out / "ranking.png").is_file()


def test_cli_errors_cleanly(tmp_path, capsys):
    from crisp_gym.sim2real.cli import main

    assert main(["diagnose", "--real", str(tmp_path / "missing.npz"), "-o", str(tmp_path / "r")]) == 2
    assert "not found" in capsys.readouterr().err
