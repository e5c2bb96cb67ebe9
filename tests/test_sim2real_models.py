"""The servo pendulum's actuator law against the DC motor it models, and the gap tool's own
reading of that law."""

import mujoco
import numpy as np
import pytest

from crisp_gym.sim2real.effects.joints import GainScale
from crisp_gym.sim2real.effects.loads import actuator_torque
from crisp_gym.sim2real.log import RealLog
from crisp_gym.sim2real.models import SERVO_ACTUATOR, SERVO_JOINT, ServoConfig, build_servo_pendulum
from crisp_gym.sim2real.replay import bind


def _joint_torque(model: mujoco.MjModel, q: float, qdot: float, ctrl: float) -> float:
    """What the actuator applies to the hinge: its force and its passive damping."""
    data = mujoco.MjData(model)
    data.qpos[0], data.qvel[0], data.ctrl[0] = q, qdot, ctrl
    mujoco.mj_forward(model, data)
    return float(data.qfrc_actuator[0] + data.qfrc_damper[0])


def _bound_log(model: mujoco.MjModel, enabled: np.ndarray | None = None):
    """A short servo log (its samples do not matter here) bound to ``model``."""
    t = np.arange(20) * 0.01
    log = RealLog(time=t, qpos=np.zeros((20, 1)), ctrl=np.zeros((20, 1)), joint_names=(SERVO_JOINT,),
                  actuator_names=(SERVO_ACTUATOR,), ctrl_enabled=enabled)
    return bind(log, model, validate=False)


@pytest.mark.parametrize("error", [0.01, -0.02, 0.5, -1.5])
@pytest.mark.parametrize("qdot", [-4.0, 0.0, 3.0])
def test_servo_is_a_pwm_clipped_dc_motor(error, qdot):
    """The firmware clips the duty cycle, not the torque: at full duty the back-EMF still brakes,
    torque = kt / R (vin clip(duty) - kt qdot), whether the servo is saturated or not."""
    cfg = ServoConfig()
    duty = np.clip(cfg.duty_per_rad * error, -1.0, 1.0)
    expected = cfg.kt / cfg.resistance * (cfg.vin * duty - cfg.kt * qdot)
    got = _joint_torque(build_servo_pendulum(cfg), 0.3, qdot, 0.3 + error)
    assert got == pytest.approx(expected, rel=1e-9, abs=1e-12)


def test_saturated_servo_moving_against_its_command_brakes_harder():
    """At full duty a servo driven backwards by its load brakes by its back-EMF on top of the
    stall torque (the law that clamps the damping with the PD force loses that)."""
    cfg = ServoConfig()
    stall = cfg.torque_limit
    assert _joint_torque(build_servo_pendulum(cfg), 0.0, -3.0, 2.0) > stall + 0.1


def test_gap_tool_reads_the_servo_torque_as_mujoco_applies_it():
    """``actuator_torque`` (the load the gear friction grows with) against MuJoCo's own forces,
    at states below and at saturation, with the actuator on and off."""
    model = build_servo_pendulum(ServoConfig(kp=800))
    tr = _bound_log(model)
    rng = np.random.default_rng(0)
    q, qdot, ctrl = rng.uniform(-1, 1, 20), rng.uniform(-5, 5, 20), rng.uniform(-2, 2, 20)
    enabled = rng.random((20, 1)) < 0.7
    got = actuator_torque(model, tr, np.array([0]), ctrl[:, None], enabled, q[:, None], qdot[:, None])[:, 0]
    expected = [_joint_torque(model, *state) if on else 0.0 for *state, on in zip(q, qdot, ctrl, enabled[:, 0])]
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)


def test_a_servo_switched_off_neither_drives_nor_brakes():
    """Torque disabled is an open circuit: no PD force and no back-EMF damping."""
    model = build_servo_pendulum()
    off = _bound_log(model, np.arange(20)[:, None] < 10).model_for(model, (False,))
    assert _joint_torque(model, 0.2, 2.0, 1.0) != 0.0
    assert _joint_torque(off, 0.2, 2.0, 1.0) == 0.0


def test_a_pd_gain_scale_scales_the_back_emf_too():
    """The gain effect scales the whole PD law, its damping included, below saturation."""
    model = build_servo_pendulum()
    scaled = model.__copy__()
    GainScale().edit_model(scaled, np.array([1.7]), _bound_log(model))
    state = (0.2, 1.5, 0.21)  # 0.01 rad of error: far from full duty
    assert _joint_torque(scaled, *state) == pytest.approx(1.7 * _joint_torque(model, *state), rel=1e-9)
