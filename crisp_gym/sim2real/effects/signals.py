"""Effects on the signals: actuator and sensor delay, backlash (a play operator on the command),
encoder bias."""

from __future__ import annotations

import numpy as np

from crisp_gym.sim2real.effects.base import Effect, Param, Signals
from crisp_gym.sim2real.replay import Trajectory

# A play's half-width, for the play operator and the gear alike: bounds, step and start points.
HALF_WIDTH = Param("half_width", 0.01, 0.0, 0.2, 5e-4, "rad")
HALF_WIDTH_STARTS = (0.003, 0.01, 0.03, 0.08)


def _shift(signal: np.ndarray, shift: float) -> np.ndarray:
    """``signal`` sampled ``shift`` samples later (negative: earlier), linearly
    interpolated and clamped at the ends."""
    n = len(signal)
    pos = np.clip(np.arange(n) - shift, 0, n - 1)
    i0 = np.floor(pos).astype(int)
    i1 = np.minimum(i0 + 1, n - 1)
    w = (pos - i0)[:, None] if signal.ndim == 2 else pos - i0
    return signal[i0] * (1 - w) + signal[i1] * w


class ActuatorDelay(Effect):
    """Commands reach the actuators ``delay`` seconds late (bus, filtering, firmware): all of
    them, only the drives of one joint (one slow servo on a bus), or each joint's drives with
    a delay of their own."""

    name, family, focus_allowed, on_drives = "actuator_delay", "delay", True, True

    def params(self, tr: Trajectory) -> list[Param]:
        return self.expand([Param("delay", 0.01, 0.0, 0.15, 0.25 * tr.log.dt, "s")], tr)

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        n = len(self.params(tr))
        return [np.full(n, d) for d in (0.004, 0.012, 0.025, 0.045, 0.07, 0.1)]

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        if self.joints is None and not self.per_joint:
            return Signals(_shift(sig.ctrl, x[0] * tr.nsub / tr.log.dt), sig.qpos, sig.qvel)
        ctrl = sig.ctrl.copy()
        cols = self.columns(tr)
        for drives, delay in zip(self.actuators_of(tr, cols), self.values(x, tr)):
            if len(drives):
                ctrl[:, drives] = _shift(sig.ctrl[:, drives], delay * tr.nsub / tr.log.dt)
        return Signals(ctrl, sig.qpos, sig.qvel)


class SensorDelay(Effect):
    """The logged position lags the true one by ``delay`` seconds."""

    name, family, per_joint_allowed = "sensor_delay", "delay", False

    def params(self, tr: Trajectory) -> list[Param]:
        return [Param("delay", 0.01, 0.0, 0.15, 0.25 * tr.log.dt, "s")]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([d]) for d in (0.004, 0.012, 0.025, 0.045, 0.07, 0.1)]

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        k = x[0] / tr.log.dt
        return Signals(sig.ctrl, _shift(sig.qpos, -k), _shift(sig.qvel, -k))

    def measure(self, qpos: np.ndarray, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        return _shift(qpos, x[0] / tr.log.dt)

    def measure_velocity(self, qvel: np.ndarray, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        return _shift(qvel, x[0] / tr.log.dt)


class Backlash(Effect):
    """Play between command and joint: the effective target moves only once the command
    has crossed a dead band of half-width ``gap`` (a play operator on the command), on every
    drive or (confined to a joint) on that joint's drives only."""

    name, family, per_joint_allowed, focus_allowed, on_drives = "backlash", "backlash", False, True, True

    def params(self, tr: Trajectory) -> list[Param]:
        return [HALF_WIDTH]

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        return [np.array([b]) for b in HALF_WIDTH_STARTS]

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        acts = np.concatenate(self.actuators_of(tr, self.columns(tr)))
        if not len(acts):
            return sig
        b = x[0]
        u = sig.ctrl[::tr.nsub, acts]
        y = np.empty_like(u)
        y[0] = u[0]
        for k in range(1, len(u)):
            y[k] = np.clip(y[k - 1], u[k] - b, u[k] + b)
        ctrl = sig.ctrl.copy()
        ctrl[:, acts] = np.repeat(y, tr.nsub, axis=0)[:len(ctrl)]
        return Signals(ctrl, sig.qpos, sig.qvel)


class EncoderBias(Effect):
    """A constant offset between the encoder's zero and the model's joint zero."""

    name, family = "encoder_bias", "encoder_bias"

    def params(self, tr: Trajectory) -> list[Param]:
        return self.expand([Param("bias", 0.0, -0.3, 0.3, 1e-3, "rad")], tr)

    def starts(self, tr: Trajectory) -> list[np.ndarray]:
        # Not convex once contacts are involved: a biased leg starts its windows in or above the ground.
        n = len(self.params(tr))
        return [np.full(n, b) for b in (0.0, -0.01, 0.01, -0.03, 0.03, -0.06, 0.06)]

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        qpos = sig.qpos.copy()
        qpos[:, self.columns(tr)] -= self.values(x, tr)
        return Signals(sig.ctrl, qpos, sig.qvel)

    def measure(self, qpos: np.ndarray, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        out = qpos.copy()
        out[:, self.columns(tr)] += self.values(x, tr)
        return out
