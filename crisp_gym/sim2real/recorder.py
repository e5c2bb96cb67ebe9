"""Record a simulated rollout in the real-log format, so that sim logs (an env's policy
rollout, a synthetic benchmark case) go through exactly the same diagnosis as real ones."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from crisp_gym.sim2real.log import RealLog, save_log

_SCALAR_JOINTS = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


class LogRecorder:
    """Append ``(time, qpos, qvel, ctrl)`` of a model's scalar joints and actuators.

    Call :meth:`record` once per control step (after setting ``data.ctrl`` and before or
    after stepping, consistently); :meth:`log` returns the :class:`RealLog`.
    """

    def __init__(self, model: mujoco.MjModel, joints: list[str] | None = None,
                 actuators: list[str] | None = None) -> None:
        if joints is None:
            joints = [model.joint(j).name for j in range(model.njnt) if model.jnt_type[j] in _SCALAR_JOINTS]
        if actuators is None:
            actuators = [model.actuator(a).name for a in range(model.nu)]
        self._qadr = np.array([model.jnt_qposadr[model.joint(n).id] for n in joints], dtype=int)
        self._dadr = np.array([model.jnt_dofadr[model.joint(n).id] for n in joints], dtype=int)
        self._act = np.array([model.actuator(n).id for n in actuators], dtype=int)
        self.joints, self.actuators = tuple(joints), tuple(actuators)
        self._rows: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []

    def record(self, data: mujoco.MjData) -> None:
        self._rows.append((float(data.time), data.qpos[self._qadr].copy(), data.qvel[self._dadr].copy(),
                           data.ctrl[self._act].copy()))

    def log(self, meta: dict | None = None) -> RealLog:
        if not self._rows:
            raise ValueError("nothing recorded: call record(data) at every control step first")
        time, qpos, qvel, ctrl = (np.array(c) for c in zip(*self._rows))
        return RealLog(time=time, qpos=qpos, ctrl=ctrl, joint_names=self.joints, actuator_names=self.actuators,
                       qvel=qvel, meta=meta or {"format": "recorder"})

    def save(self, path: str | Path, meta: dict | None = None) -> Path:
        return save_log(self.log(meta), path)
