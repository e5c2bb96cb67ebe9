"""Adapters from the real formats in the wild to :class:`RealLog` (plus the model each
was recorded on): the Dynamixel servo JSON logs and the Go2 ``traj_*.npz``."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np

from crisp_gym.npz import read_npz
from crisp_gym.sim2real.log import RealLog
from crisp_gym.sim2real.models import (
    GO2_JOINTS,
    GO2_KD,
    GO2_KP,
    SERVO_ACTUATOR,
    SERVO_JOINT,
    ServoConfig,
    build_servo_pendulum_spec,
    load_go2_fixed_base_spec,
)

_SERVO_HEADER = ("mass", "length", "kp", "vin", "dt")
_SERVO_ENTRY = ("position", "goal_position", "timestamp", "torque_enable")


def load_servo_json(path: str | Path) -> tuple[RealLog, mujoco.MjSpec]:
    """A servo JSON log (header ``{mass, length, kp, vin, motor, trajectory, dt}``,
    ``entries[]`` with ``position, speed, goal_position, torque_enable, timestamp`` in
    rad, rad/s, s) and the pendulum model built from its header (a spec: ``.compile()`` it
    for an ``MjModel``; :func:`~crisp_gym.sim2real.diagnose.diagnose` takes either).

    ``torque_enable`` false becomes ``ctrl_enabled`` false: the servo exerts no torque.
    The logged ``speed`` is not used as ``qvel``: it is the servo's own coarse estimate
    and the replay's smoothed derivative of ``position`` is more consistent with it.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"servo log not found: {path}")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path} is not valid JSON ({err})") from None
    missing = [k for k in _SERVO_HEADER if k not in data] if isinstance(data, dict) else list(_SERVO_HEADER)
    if missing or "entries" not in data:
        raise ValueError(f"{path} is not a servo JSON log: missing {missing or ['entries']} "
                         f"(expected header {list(_SERVO_HEADER)} and entries[])")
    entries = data["entries"]
    try:
        col = {k: np.array([e[k] for e in entries], dtype=float) for k in _SERVO_ENTRY}
        cfg = ServoConfig(mass=float(data["mass"]), length=float(data["length"]), kp=float(data["kp"]),
                          vin=float(data["vin"]))
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: the header needs numbers {list(_SERVO_HEADER)} and every entry numbers "
                         f"{list(_SERVO_ENTRY)} ({type(err).__name__}: {err})") from None
    meta = {"format": "servo_json", "source": str(path), "kp": cfg.kp, "vin": cfg.vin,
            "trajectory": data.get("trajectory", ""), "motor": data.get("motor", "")}
    log = RealLog(time=col["timestamp"], qpos=col["position"][:, None], ctrl=col["goal_position"][:, None],
                  joint_names=(SERVO_JOINT,), actuator_names=(SERVO_ACTUATOR,),
                  ctrl_enabled=col["torque_enable"].astype(bool)[:, None], meta=meta)
    return log, build_servo_pendulum_spec(cfg)


def load_go2_npz(path: str | Path, xml: str | Path | None = None, kp: float = GO2_KP,
                 kd: float = GO2_KD) -> tuple[RealLog, mujoco.MjSpec]:
    """A Go2 log (``time``, ``dof_pos``, ``des_dof_pos`` (T, 12) in the order
    FL/FR/RL/RR x hip/thigh/calf) and the fixed-base model from ``xml`` (default:
    ``go2.xml`` beside the log), as a spec."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Go2 log not found: {path}")
    xml = Path(xml) if xml is not None else path.with_name("go2.xml")
    z = read_npz(path, "Go2 log")
    missing = [k for k in ("time", "dof_pos", "des_dof_pos") if k not in z]
    if missing:
        raise ValueError(f"{path} is not a Go2 log: missing {missing}")
    time, q, qd = (np.asarray(z[k], dtype=float) for k in ("time", "dof_pos", "des_dof_pos"))
    if q.shape[1:] != (12,) or qd.shape != q.shape:
        raise ValueError(f"Go2 dof_pos/des_dof_pos must be (T, 12), got {q.shape} and {qd.shape}")
    spec = load_go2_fixed_base_spec(xml, kp, kd)
    actuators = tuple(a.name for a in spec.actuators)
    log = RealLog(time=time, qpos=q, ctrl=qd, joint_names=GO2_JOINTS, actuator_names=actuators,
                  meta={"format": "go2_npz", "source": str(path), "kp": kp, "kd": kd})
    return log, spec
