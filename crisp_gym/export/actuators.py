"""The humanoid's actuation as plain data: what URDF files and policy runtimes need but cannot read from MJCF."""

from __future__ import annotations

import mujoco

from crisp_gym.humanoid import HumanoidConfig, build_humanoid, servo_damping


def joint_servos(model: mujoco.MjModel) -> dict[int, int]:
    """Joint id -> id of the actuator driving it (joint-transmission actuators only)."""
    return {int(model.actuator_trnid[a, 0]): a for a in range(model.nu)
            if int(model.actuator_trntype[a]) == mujoco.mjtTrn.mjTRN_JOINT}


def actuator_table(model: mujoco.MjModel | None = None) -> dict:
    """PD gains, torque limits, armature and ranges of every actuated joint of ``model``.

    ``model`` defaults to :func:`crisp_gym.humanoid.build_humanoid`. The actuators are MuJoCo
    position servos whose damping acts outside the torque limit (the humanoid's:
    ``torque = clip(kp (target − q), ±effort_limit) − kd q̇``) or inside it
    (``clip(kp (target − q) − kd q̇, ±effort_limit)``); ``actuator`` says which.
    """
    model = model if model is not None else build_humanoid(HumanoidConfig())
    servos = sorted(joint_servos(model).items())
    passive = any(model.actuator_damping[a] > 0 for _, a in servos)
    kd = servo_damping(model)
    joints = {}
    for j, a in servos:
        dof = model.jnt_dofadr[j]
        joints[model.joint(j).name] = {
            "kp": float(model.actuator_gainprm[a, 0]),
            "kd": float(kd[a]),
            "effort_limit": float(model.actuator_forcerange[a, 1]) if model.actuator_forcelimited[a] else None,
            "armature": float(model.dof_armature[dof]),
            "lower": float(model.jnt_range[j, 0]), "upper": float(model.jnt_range[j, 1]),
        }
    return {
        "actuator": ("position servo: torque = clip(kp * (target - q), -effort_limit, effort_limit) - kd * qdot"
                     if passive else
                     "position servo: torque = clip(kp * (target - q) - kd * qdot, -effort_limit, effort_limit)"),
        "units": {"kp": "N*m/rad", "kd": "N*m*s/rad", "effort_limit": "N*m", "armature": "kg*m^2",
                  "lower": "rad", "upper": "rad"},
        "timestep": float(model.opt.timestep),
        "joints": joints,
    }
