"""The walk plan: a path (straight or an arc), footsteps anchored on treads and platform edges and
filled with even steps, and pelvis keyframes whose progress and sway are those of a linear inverted
pendulum over the feet (:mod:`crisp_gym.balance`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import PchipInterpolator

from crisp_gym.balance import GRAVITY
from crisp_gym.synth.scenes import Level
from crisp_gym.synth.skeleton import SIDE, Skeleton


@dataclass(frozen=True)
class WalkPath:
    """A planar path: a straight line along +x (``curvature == 0``) or a circular arc from the origin."""

    curvature: float = 0.0

    def heading(self, s: np.ndarray) -> np.ndarray:
        return self.curvature * np.asarray(s, dtype=float)

    def frame(self, s: np.ndarray, lateral: np.ndarray) -> np.ndarray:
        """(..., 2) world xy of arc length ``s`` shifted by ``lateral`` along the left normal."""
        s = np.asarray(s, dtype=float)
        k = self.curvature
        psi = k * s
        if abs(k) < 1e-9:
            base = np.stack([s, np.zeros_like(s)], axis=-1)
        else:
            base = np.stack([np.sin(psi) / k, (1 - np.cos(psi)) / k], axis=-1)
        normal = np.stack([-np.sin(psi), np.cos(psi)], axis=-1)
        return base + np.asarray(lateral, dtype=float)[..., None] * normal


@dataclass(frozen=True)
class GaitParams:
    """Per-clip gait parameters (drawn from the seed by :func:`sample_gait`).

    Attributes:
        speed: nominal level-walking speed (m/s).
        step_length: nominal level step length, ankle to ankle along the path (m).
        step_width: lateral distance between the feet (m).
        stair_step_time: duration of one step that changes level (s).
        double_support: fraction of a step with both feet on the ground.
        sway: lateral pelvis shift towards the stance foot (m).
        bob: pelvis rise at mid-stance above the standing height (m).
        toe_out: outward yaw of each foot (rad).
        arm_swing: shoulder swing per metre of foot lead over the pelvis (rad/m).
        curvature: path curvature for level walks (1/m; 0 is straight).
    """

    speed: float
    step_length: float
    step_width: float
    stair_step_time: float
    double_support: float
    sway: float
    bob: float
    toe_out: float
    arm_swing: float
    curvature: float

    @property
    def step_time(self) -> float:
        return self.step_length / self.speed


def sample_gait(rng: np.random.Generator, curved: bool = False) -> GaitParams:
    """Gait parameters of an adult of about 1.70 m, within the ranges of gait-lab norms."""
    return GaitParams(
        speed=round(rng.uniform(1.0, 1.35), 3), step_length=round(rng.uniform(0.55, 0.68), 3),
        step_width=round(rng.uniform(0.17, 0.21), 3), stair_step_time=round(rng.uniform(0.70, 0.85), 3),
        double_support=0.22, sway=round(rng.uniform(0.02, 0.035), 3), bob=0.012,
        toe_out=round(np.deg2rad(rng.uniform(3.0, 8.0)), 4), arm_swing=0.5,
        curvature=round(rng.uniform(-0.2, 0.2), 3) if curved else 0.0)


@dataclass
class FootMove:
    """One swing of a foot from (s0, z0) to (s1, z1) between lift and land (seconds), after a
    heel-off that pitches the foot by ``heel`` rad about the toe joint over ``roll`` seconds."""

    lift: float
    land: float
    s0: float
    z0: float
    s1: float
    z1: float
    heel: float = 0.0
    roll: float = 0.0


@dataclass
class MotionPlan:
    """Footsteps and pelvis keyframes of a whole clip (mutable while it is being built)."""

    feet: list[tuple[float, float]]  # current (s, z) of the left and right ankle
    moves: list[list[FootMove]] = field(default_factory=lambda: [[], []])
    keys: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    end: float = 0.0

    def key(self, channel: str, t: float, value: float) -> None:
        self.keys.setdefault(channel, []).append((float(t), float(value)))

    def pose(self, t: float, s: float, lateral: float, z: float, pitch: float = 0.0,
             spine: float = 0.0, arms: float = 0.0) -> None:
        """Keyframe every pelvis channel at once."""
        for channel, value in (("s", s), ("lat", lateral), ("z", z), ("pitch", pitch), ("spine", spine),
                               ("arms", arms)):
            self.key(channel, t, value)

    def channel(self, name: str, t: np.ndarray) -> np.ndarray:
        """Shape-preserving interpolation of a channel's keyframes (held constant outside them)."""
        keys = sorted(self.keys[name])
        times = np.array([k[0] for k in keys])
        values = np.array([k[1] for k in keys])
        if np.any(np.diff(times) <= 1e-6):
            raise RuntimeError(f"channel {name!r} has keyframes at the same time: {times}")
        if len(times) == 1:
            return np.full_like(t, values[0])
        return PchipInterpolator(times, values)(np.clip(t, times[0], times[-1]))


PELVIS_AHEAD = 0.04  # m: the standing pelvis is above the mid-foot, ahead of the ankles


def add_walk(plan: MotionPlan, t0: float, targets: list[tuple[float, float]], first: int, gait: GaitParams,
              skel: Skeleton, stand_after: float = 0.6) -> None:
    """Append footsteps to ``targets`` ((s, z) ankle positions, alternating feet from ``first``).

    Pelvis keyframes: over the stance foot (shifted towards it, at its height plus the bob) at
    mid-swing, between the feet in double support, standing still ``stand_after`` s after the
    last landing.
    """
    stand = skel.pelvis_height - 0.012
    t = t0
    landed = [t0 - 1.0, t0 - 1.0]  # standing feet have been planted for a while
    feet_before = [s for s, _ in plan.feet]
    for k, (s, z) in enumerate(targets):
        foot = first if k % 2 == 0 else 1 - first
        other = 1 - foot
        (s_prev, z_prev), (s_o, z_o) = plan.feet[foot], plan.feet[other]
        change = abs(z - z_prev) > 0.02
        step = gait.stair_step_time if change else gait.step_time
        swing = step * (1 - gait.double_support)
        # Heel-off before the lift: larger and earlier when the other foot has just stepped down
        # (the body sank while this foot stayed on the higher surface) or when stepping up.
        down_before = k > 0 and targets[k - 1][1] < z_prev - 0.02
        heel = 0.5 if (z - z_prev > 0.02 or down_before) else 0.35
        roll = min(0.6, 0.8 * (t - landed[foot])) if down_before else min(0.3, 0.45 * (t - landed[foot]))
        plan.moves[foot].append(FootMove(t, t + swing, s_prev, z_prev, s, z, heel=heel, roll=roll))
        landed[foot] = t + swing
        lean = 0.10 if z - z_prev > 0.02 else 0.04
        plan.pose(t + swing / 2, s_o + PELVIS_AHEAD, SIDE[other] * gait.sway, z_o + stand + gait.bob, pitch=lean)
        plan.feet[foot] = (s, z)
        t += swing
        if k < len(targets) - 1:
            plan.pose(t + step * gait.double_support / 2, (s + s_o) / 2 + PELVIS_AHEAD, 0.0,
                      (z + z_o) / 2 + stand - gait.bob, pitch=lean)
            t += step * gait.double_support
    (s_l, z_l), (s_r, z_r) = plan.feet
    plan.end = t + stand_after
    for when in (t + 0.6 * stand_after, plan.end):  # twice, so the motion comes to rest
        plan.pose(when, (s_l + s_r) / 2 + PELVIS_AHEAD, 0.0, max(z_l, z_r) + stand)
    _balance_pelvis(plan, t0 - _WALK_PREPARATION, feet_before, gait, skel)


_WALK_PREPARATION = 0.3  # s before the first lift in which the body starts to shift over the stance foot


_ZMP_HEEL, _ZMP_TOE = 0.0, 0.08  # m ahead of the ankle: the centre of pressure rolls from heel to toe


_BALANCE_DT = 1.0 / 60.0  # s: the pendulum's time step (keys are written at this rate)
_BALANCE_JERK_WEIGHT = 1e-4  # m of centre-of-pressure error that weigh as much as 1 m/s³ of jerk


def _balance_pelvis(plan: MotionPlan, start: float, feet: list[float], gait: GaitParams, skel: Skeleton) -> None:
    """Replace the pelvis's path position and sway (channels ``s`` and ``lat``) of a walk from
    ``start`` (at rest, feet at ``feet``) to ``plan.end`` (at rest) by ones a body can balance on.

    Keyframes over the stance foot accelerated the body by up to ±7 m/s² (a centre of pressure
    up to 1.5 m outside the feet, stopping a walk: :mod:`crisp_gym.balance`). Instead the pelvis
    follows the linear inverted pendulum whose centre of pressure tracks the feet (Kajita et al.
    2003): under the stance foot, rolling from heel to toe, moving to the next foot in double
    support.
    """
    moves = sorted((m.lift, m.land, foot, m.s1) for foot in range(2) for m in plan.moves[foot] if m.lift >= start)
    ends = np.array([start, plan.end])
    knots_t = [start]
    knots = {"s": [plan.channel("s", ends)[0]], "lat": [plan.channel("lat", ends)[0]]}
    for lift, land, foot, landed_at in moves:
        stance = 1 - foot
        knots_t += [lift, land]
        knots["s"] += [feet[stance] + _ZMP_HEEL, feet[stance] + _ZMP_TOE]
        knots["lat"] += [SIDE[stance] * gait.step_width / 2] * 2
        feet[foot] = landed_at
    knots_t.append(plan.end)
    t = np.arange(start, plan.end + _BALANCE_DT / 2, _BALANCE_DT)
    for channel, values in knots.items():
        values.append(plan.channel(channel, ends)[1])
        path = _pendulum_path(np.interp(t, knots_t, values), skel.pelvis_height, _BALANCE_DT)
        plan.keys[channel] = [key for key in plan.keys[channel] if key[0] < start - 1e-6] + list(zip(t, path))


def _pendulum_path(cop: np.ndarray, height: float, dt: float) -> np.ndarray:
    """Positions of a linear inverted pendulum of ``height`` whose centre of pressure follows
    ``cop`` (sampled every ``dt`` s), at rest at ``cop``'s ends: least squares over
    ``c - height / g * c'' = cop`` with a small jerk penalty."""
    n = len(cop)
    pendulum = np.zeros((n - 2, n))
    rows = np.arange(n - 2)
    stiffness = height / GRAVITY / dt**2
    pendulum[rows, rows], pendulum[rows, rows + 1], pendulum[rows, rows + 2] = -stiffness, 1 + 2 * stiffness, -stiffness
    jerk = np.zeros((n - 3, n))
    for j, coefficient in enumerate((-1.0, 3.0, -3.0, 1.0)):
        jerk[np.arange(n - 3), np.arange(n - 3) + j] = coefficient * _BALANCE_JERK_WEIGHT / dt**3
    rest = np.zeros((4, n))
    rest[[0, 1, 2, 3], [0, 1, n - 2, n - 1]] = 1e3  # two equal samples at each end: at rest
    rhs = np.concatenate([cop[1:-1], np.zeros(n - 3), 1e3 * cop[[0, 0, -1, -1]]])
    return np.linalg.lstsq(np.vstack([pendulum, jerk, rest]), rhs, rcond=None)[0]


def even_positions(a: float, b: float, step: float) -> list[float]:
    """Evenly spaced positions after ``a`` up to and including ``b``, no step longer than ``step``."""
    n = max(1, int(np.ceil((b - a) / step - 1e-9)))
    return [a + (b - a) * i / n for i in range(1, n + 1)]


def footsteps(anchors: list[tuple[float, float]], start: float, step: float) -> list[tuple[float, float]]:
    """Footstep targets through ``anchors`` ((s, z), in order), filling level stretches evenly,
    ending with the trailing foot placed beside the leading one."""
    targets: list[tuple[float, float]] = []
    s_prev, z_prev = start, anchors[0][1]
    for s, z in anchors:
        if abs(z - z_prev) > 1e-9:
            targets.append((s, z))
        else:
            targets += [(x, z) for x in even_positions(s_prev, s, step)]
        s_prev, z_prev = s, z
    targets.append(targets[-1])
    return targets


# Foot placement margins (m): toe or heel to a higher edge, and a foot fully on a level.
_EDGE_MARGIN = 0.02
_LEVEL_MARGIN = 0.04


def _tread_ankle(level: Level, skel: Skeleton, higher_before: bool, higher_after: bool) -> float:
    """Ankle x on a level: the foot centred, but kept off the riser of a higher neighbour."""
    x = (level.x0 + level.x1) / 2 - (skel.toe - skel.heel) / 2
    if higher_after:
        x = min(x, level.x1 - _EDGE_MARGIN - skel.toe)
    if higher_before:
        x = max(x, level.x0 + _EDGE_MARGIN + skel.heel)
    return x


def terrain_anchors(levels: list[Level], before: float, after: float, skel: Skeleton,
                     stop_on_last: bool, step: float) -> list[tuple[float, float]]:
    """Anchor footsteps over ``levels`` (in walking order) from a stretch at height ``before``.

    The last foot before the first edge keeps its toe clear of a riser; short levels (treads)
    get one foot each; long ones (platforms, landings) a foot just past their near edge and one
    before their far edge. The walk stops on the last level (``stop_on_last``) or continues
    onto a stretch at height ``after`` for two more steps.
    """
    first = levels[0]
    toe_gap = _EDGE_MARGIN + (0.05 if first.z > before else 0.0)
    anchors = [(first.x0 - toe_gap - skel.toe, before)]
    heights = [before] + [lv.z for lv in levels] + [after]
    for i, level in enumerate(levels):
        lower, higher = heights[i], heights[i + 2]
        if level.x1 - level.x0 < skel.heel + skel.toe + 2 * _LEVEL_MARGIN:
            anchors.append((_tread_ankle(level, skel, lower > level.z, higher > level.z), level.z))
            continue
        near = level.x0 + skel.heel + _LEVEL_MARGIN
        anchors.append((near, level.z))
        if stop_on_last and i == len(levels) - 1:
            return anchors
        far = level.x1 - skel.toe - _LEVEL_MARGIN
        if far > near + 0.1:
            anchors.append((far, level.z))
    end = levels[-1].x1 + skel.heel + _LEVEL_MARGIN + 0.05
    return anchors + [(end, after), (end + step, after)]
