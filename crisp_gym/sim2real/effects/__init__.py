"""The library of candidate unmodelled effects.

An effect is a named, parametric change either to the model (friction, damping, gains,
masses, the ground...) or to the signals (a command delay, an encoder bias...). It is
shared by its target joints (one parameter), or per joint (one parameter each).
Adding an effect is one small subclass: say which parameters it has and override
``edit_model`` and/or ``edit_signals`` (and ``measure``, if it acts on the sensor, so
that synthetic logs can be generated with it), or ``friction`` for dry friction that
depends on the state (load-dependent and Stribeck friction; the replay then steps the
model one log sample at a time).

Identification treats delays on the command and on the sensor as one family: when the
servo closes its loop on its own encoder, both shift the response by the same amount in
an open-loop replay and cannot be told apart from position logs.

The effects by what they change: :mod:`~crisp_gym.sim2real.effects.signals` (delays, backlash,
encoder bias), :mod:`~crisp_gym.sim2real.effects.gear_play` (a gear's play, with the motor's rotor
added to the model), :mod:`~crisp_gym.sim2real.effects.joints` (friction, damping, armature, gains, saturation),
:mod:`~crisp_gym.sim2real.effects.loads` (mass, centre of mass, payload, load-dependent, gearbox and
Stribeck friction) and :mod:`~crisp_gym.sim2real.effects.ground`; what they share is
:mod:`~crisp_gym.sim2real.effects.base`. This module lists them (:data:`EFFECT_TYPES`) and makes the
candidates for a log (:func:`library`).
"""

from __future__ import annotations

from crisp_gym.sim2real.effects.base import (
    CannotApply,
    Effect,
    Param,
    Signals,
    inertia_scale,
    joint_actuators,
    speed_scale,
    torque_scale,
)
from crisp_gym.sim2real.effects.ground import (
    SUPPORT_POSTURES,
    ContactSoftness,
    GroundFriction,
    GroundHeight,
    GroundTilt,
    SupportBox,
    ground_geoms,
    ground_top,
    support_points,
)
from crisp_gym.sim2real.effects.joints import Armature, CoulombFriction, GainScale, TorqueSaturation, ViscousDamping
from crisp_gym.sim2real.effects.loads import (
    ComShift,
    GearboxFriction,
    LoadFriction,
    MassScale,
    Payload,
    StribeckFriction,
    actuator_torque,
    add_point_mass,
    external_torque,
    joints_below,
    lever_scale,
    release_inertial_frame,
)
from crisp_gym.sim2real.effects.gear_play import GearPlay, add_rotors, limit_compliance, rotor_track
from crisp_gym.sim2real.effects.signals import ActuatorDelay, Backlash, EncoderBias, SensorDelay
from crisp_gym.sim2real.replay import Trajectory

__all__ = [
    "EFFECT_TYPES", "FAMILIES", "SUPPORT_POSTURES", "ActuatorDelay", "Armature", "Backlash", "CannotApply",
    "ComShift", "ContactSoftness", "CoulombFriction", "Effect", "EncoderBias", "GainScale", "GearPlay",
    "GearboxFriction", "GroundFriction", "GroundHeight", "GroundTilt", "LoadFriction", "MassScale", "Param",
    "Payload", "SensorDelay", "Signals", "StribeckFriction", "SupportBox", "TorqueSaturation", "ViscousDamping",
    "actuator_torque", "add_point_mass", "add_rotors", "check_families", "external_torque", "ground_geoms",
    "ground_top", "inertia_scale", "joint_actuators", "joints_below", "lever_scale", "library",
    "limit_compliance", "release_inertial_frame", "rotor_track", "speed_scale", "support_points", "torque_scale",
]


EFFECT_TYPES: tuple[type[Effect], ...] = (
    ActuatorDelay, SensorDelay, CoulombFriction, ViscousDamping, Armature, GainScale, TorqueSaturation,
    Backlash, GearPlay, EncoderBias, MassScale, ComShift, Payload, LoadFriction, GearboxFriction, StribeckFriction,
    GroundFriction, ContactSoftness, GroundHeight, GroundTilt, SupportBox,
)
"""Every effect of the library, in the order the report lists them."""


FAMILIES: tuple[str, ...] = tuple(dict.fromkeys(t.family for t in EFFECT_TYPES))


def check_families(families: tuple[str, ...]) -> None:
    """ValueError naming every entry of ``families`` that is no family of :data:`FAMILIES`."""
    unknown = [f for f in families if f not in FAMILIES]
    if unknown:
        raise ValueError(f"unknown effect families {unknown}; the library's are {', '.join(FAMILIES)}")


def library(tr: Trajectory, focus: str | None = None, families: tuple[str, ...] | None = None) -> list[Effect]:
    """Candidate effects for a log: each effect shared by all joints; for joint effects
    on a multi-joint log, also one confined to ``focus`` (the joint with the largest gap),
    for ``below_focus`` effects one confined to each body below it (:func:`joints_below`),
    and one with a parameter per joint. Effects that cannot act (no ground) are left out."""
    out: list[Effect] = []
    n = len(tr.log.joint_names)
    for kind in EFFECT_TYPES:
        if families is not None and kind.family not in families:
            continue
        variants = [kind()]
        if n > 1 and focus is not None and (kind.per_joint_allowed or kind.focus_allowed):
            variants.append(kind(joints=(focus,)))
        if n > 1 and focus is not None and kind.below_focus:
            variants.extend(kind(joints=(j,)) for j in joints_below(tr, focus))
        if n > 1 and kind.per_joint_allowed:
            variants.append(kind(per_joint=True))
        out.extend(v for v in variants if v.applicable(tr))
    return out
