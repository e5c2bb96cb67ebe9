"""Synthetic benchmark clips: box scenes with a procedurally generated, kinematically consistent motion.

Every clip is a scene of box primitives (a floor plus stairs, a platform or a box seat) and a
reference motion of the project's humanoid whose contacts are true by construction: the
footsteps are planned onto the support surfaces, the legs are solved by analytic two-link IK so
a stance foot sits flat and still on its surface, swing feet follow arcs that are searched to
clear every edge, and the seated pelvis height is solved against the real humanoid geometry.
Because the ground truth is exact, these clips measure the rest of the project (reconstruction,
contact detection, tracking) without the noise of a video.

The generator works in a path frame: arc length ``s`` along a planar path (straight, or an arc
for ``flat_walk``) and a lateral offset. The motion is assembled in stages:

1. a footstep plan (which foot lands where and when; anchors on treads and platform edges,
   filled with even steps on level ground) and pelvis keyframes per channel (progress, sway,
   height, lean), interpolated with shape-preserving cubic splines so nothing overshoots; while
   walking, progress and sway are those of a linear inverted pendulum whose centre of pressure
   follows the feet, so that a body can balance on the motion (:mod:`crisp_gym.balance`);
2. swing arcs whose lift height is the smallest that keeps the foot clear of all boxes;
3. the pelvis height limited by what the legs can reach, with small vertical accelerations;
4. leg IK (hip's three hinges, knee flexion, ankle keeping the foot flat), counter-swinging arms,
   trunk lean, a level head; then a check with MuJoCo forward kinematics that lowers the pelvis
   where a stance foot does not reach its surface.

:func:`make_clip` returns ``(boxes, motion, meta)``; :func:`bundle_clips` writes the clips shipped
in ``assets/clips`` and the bundled ``assets/registry.yaml`` (``python -m crisp_gym.reconstruct.synth``).
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import mujoco
import numpy as np
import yaml
from scipy.interpolate import PchipInterpolator
from scipy.ndimage import gaussian_filter1d, maximum_filter1d
from scipy.optimize import lsq_linear
from scipy.spatial.transform import Rotation

from crisp_gym.atomic import write_text
from crisp_gym.balance import GRAVITY
from crisp_gym.bundled import BUNDLED_CLIPS, BUNDLED_REGISTRY
from crisp_gym.clip import write_clip
from crisp_gym.humanoid import (
    BODY_NAMES, DOF_NAMES, FEET, HumanoidConfig, build_humanoid, joint_range_deg,
)  # fmt: skip
from crisp_gym.metrics import box_signed_distance, scene_model, sole_points, support_tops
from crisp_gym.motion import Motion, compute_kinematics
from crisp_gym.scene import Box, floor_box

KINDS: tuple[str, ...] = ("flat_walk", "stairs_up", "stairs_down", "platform_step", "chair_sit")
"""Clip kinds :func:`make_clip` generates."""

BUNDLED: dict[str, tuple[str, int]] = {
    "flat_walk": ("flat_walk", 1),
    "stairs_up": ("stairs_up", 1),
    "stairs_down": ("stairs_down", 1),
    "platform_step": ("platform_step", 1),
    "chair_sit": ("chair_sit", 1),
}
"""Bundled clip name -> (kind, seed)."""

TAGS: dict[str, list[str]] = {
    "flat_walk": ["synthetic", "walk", "flat"],
    "stairs_up": ["synthetic", "walk", "stairs"],
    "stairs_down": ["synthetic", "walk", "stairs"],
    "platform_step": ["synthetic", "walk", "platform"],
    "chair_sit": ["synthetic", "sit", "walk"],
}

CLIPS_DIR = BUNDLED_CLIPS
REGISTRY = BUNDLED_REGISTRY

# Human-plausible ranges (metres) of the randomised scene parameters; building codes put
# risers at 0.10-0.20 m and treads (goings) at 0.25-0.35 m; chairs have 0.40-0.50 m seats.
RISER_RANGE = (0.12, 0.18)
TREAD_RANGE = (0.26, 0.35)
STAIR_COUNT_RANGE = (3, 5)
STAIR_WIDTH_RANGE = (0.9, 1.4)
PLATFORM_HEIGHT_RANGE = (0.10, 0.25)
PLATFORM_LENGTH_RANGE = (0.8, 1.2)
SEAT_HEIGHT_RANGE = (0.40, 0.48)  # above ~0.48 m the 1.70 m humanoid's feet no longer reach the floor
SEAT_DEPTH_RANGE = (0.42, 0.48)
SEAT_WIDTH_RANGE = (0.40, 0.48)

_L, _R = 0, 1
_SIDE = np.array([1.0, -1.0])  # lateral sign of the left and right foot (left is +y)
_STANCE_BODIES = (("L_Ankle", "L_Toe"), ("R_Ankle", "R_Toe"))
_SEAT_BODIES = ("Pelvis", "L_Hip", "R_Hip")
_SEAT_CONTACT_TOLERANCE = 0.005  # m: a thigh this close to the seat counts as resting on it
_SEAT_OFF_SHARE = 0.45  # of a rise (a descent): on the seat, leaning, before (after) the feet bear the body
_RISE_COM_MARGIN = -0.02  # m: centre of mass in front of the heels (negative: behind) perched and leaning
_SEAT_EDGE_CLEARANCE = 0.03  # m: the seated pelvis stays this far behind the seat's front
_SEATED_SPINE = -0.15  # rad: the seated trunk leans back a little, its weight on the seat
_PERCH_SCAN_DEPTH = 0.22  # m behind the seat's front: where the search for a perched pelvis starts
_SUPPORT_TOLERANCE = 0.005  # m: a stance foot body whose sole is this close to a box top is on it


# --------------------------------------------------------------------------- scenes


@dataclass(frozen=True)
class StairsParams:
    """A straight flight along +x with solid steps standing on the floor.

    Attributes:
        riser: height of each step (m).
        tread: horizontal depth of each tread (m).
        width: width of the flight across the walking direction (m).
        count: number of risers; ``count - 1`` treads and a top landing.
        start: x of the first riser (ascending) or of the top nosing (descending), in m.
        landing: length of the top landing along x (m).
    """

    riser: float
    tread: float
    width: float
    count: int
    start: float
    landing: float

    @property
    def top(self) -> float:
        return self.riser * self.count


@dataclass(frozen=True)
class PlatformParams:
    """A raised box to step onto and off again.

    Attributes:
        height: top of the platform above the floor (m).
        length: extent along the walking direction +x (m).
        width: extent across it (m).
        start: x of the near edge (m).
    """

    height: float
    length: float
    width: float
    start: float


@dataclass(frozen=True)
class SeatParams:
    """A box seat with an optional backrest, its front edge facing +x.

    Attributes:
        height: seat top above the floor (m).
        depth: seat extent along x (m).
        width: seat extent along y (m).
        front: x of the seat's front edge (m).
        backrest_height: backrest top above the seat (m); 0 for a stool without one.
        backrest_thickness: backrest extent along x (m).
    """

    height: float
    depth: float
    width: float
    front: float
    backrest_height: float
    backrest_thickness: float = 0.05


@dataclass(frozen=True)
class _Level:
    """A horizontal support surface along the path: x in [x0, x1] at height z."""

    x0: float
    x1: float
    z: float


def _block(x0: float, x1: float, width: float, top: float, name: str) -> Box:
    """A solid box standing on the floor (z = 0) spanning [x0, x1] along x."""
    return Box(center=[(x0 + x1) / 2, 0.0, top / 2], half_size=[(x1 - x0) / 2, width / 2, top / 2], name=name)


def _stairs_levels(p: StairsParams, descending: bool) -> list[_Level]:
    """Support levels of a flight (floor excluded), in walking order."""
    if descending:
        levels = [_Level(p.start - p.landing, p.start, p.top)]
        levels += [_Level(p.start + (j - 1) * p.tread, p.start + j * p.tread, (p.count - j) * p.riser)
                   for j in range(1, p.count)]
    else:
        levels = [_Level(p.start + (j - 1) * p.tread, p.start + j * p.tread, j * p.riser)
                  for j in range(1, p.count)]
        end = p.start + (p.count - 1) * p.tread
        levels.append(_Level(end, end + p.landing, p.top))
    return levels


def stairs_boxes(params: StairsParams, descending: bool = False) -> list[Box]:
    """Floor plus one solid block per step and the top landing.

    Ascending flights rise along +x from ``params.start``; descending ones start with the
    landing (ending at ``params.start``) and go down along +x.
    """
    _check_stairs(params)
    boxes = [floor_box()]
    for i, level in enumerate(_stairs_levels(params, descending)):
        is_landing = np.isclose(level.z, params.top)
        boxes.append(_block(level.x0, level.x1, params.width, level.z, "landing" if is_landing else f"step_{i}"))
    return boxes


def platform_boxes(params: PlatformParams) -> list[Box]:
    """Floor plus the platform block."""
    if params.height <= 0 or params.length <= 0 or params.width <= 0:
        raise ValueError(f"platform dimensions must be positive, got {params}")
    return [floor_box(), _block(params.start, params.start + params.length, params.width, params.height, "platform")]


def seat_boxes(params: SeatParams) -> list[Box]:
    """Floor, the seat block and, when ``backrest_height > 0``, a backrest behind it."""
    if min(params.height, params.depth, params.width, params.backrest_thickness) <= 0:
        raise ValueError(f"seat dimensions must be positive, got {params}")
    back = params.front - params.depth
    boxes = [floor_box(), _block(back, params.front, params.width, params.height, "seat")]
    if params.backrest_height > 0:
        boxes.append(_block(back - params.backrest_thickness, back, params.width,
                            params.height + params.backrest_height, "backrest"))
    return boxes


def _check_stairs(p: StairsParams) -> None:
    if p.riser <= 0 or p.tread <= 0 or p.width <= 0 or p.landing <= 0:
        raise ValueError(f"stair dimensions must be positive, got {p}")
    if p.count < 1:
        raise ValueError(f"a flight needs at least one riser, got count={p.count}")


def sample_stairs_params(rng: np.random.Generator, descending: bool = False) -> StairsParams:
    """Random flight within :data:`RISER_RANGE`, :data:`TREAD_RANGE`, :data:`STAIR_COUNT_RANGE`."""
    start = rng.uniform(0.9, 1.3) if descending else rng.uniform(1.3, 1.8)
    return StairsParams(
        riser=round(rng.uniform(*RISER_RANGE), 3), tread=round(rng.uniform(*TREAD_RANGE), 3),
        width=round(rng.uniform(*STAIR_WIDTH_RANGE), 3),
        count=int(rng.integers(STAIR_COUNT_RANGE[0], STAIR_COUNT_RANGE[1] + 1)),
        start=round(start, 3), landing=round(start + 0.6 if descending else rng.uniform(1.2, 1.6), 3))


def sample_platform_params(rng: np.random.Generator) -> PlatformParams:
    """Random platform within :data:`PLATFORM_HEIGHT_RANGE` and :data:`PLATFORM_LENGTH_RANGE`."""
    return PlatformParams(height=round(rng.uniform(*PLATFORM_HEIGHT_RANGE), 3),
                          length=round(rng.uniform(*PLATFORM_LENGTH_RANGE), 3),
                          width=round(rng.uniform(0.9, 1.4), 3), start=round(rng.uniform(1.2, 1.8), 3))


def sample_seat_params(rng: np.random.Generator) -> SeatParams:
    """Random seat within :data:`SEAT_HEIGHT_RANGE`, :data:`SEAT_DEPTH_RANGE`, :data:`SEAT_WIDTH_RANGE`.

    The front edge is placed behind the standing person's calves (feet at x = 0).
    """
    return SeatParams(height=round(rng.uniform(*SEAT_HEIGHT_RANGE), 3),
                      depth=round(rng.uniform(*SEAT_DEPTH_RANGE), 3),
                      width=round(rng.uniform(*SEAT_WIDTH_RANGE), 3),
                      front=round(-rng.uniform(0.08, 0.12), 3),
                      backrest_height=round(rng.uniform(0.35, 0.45), 3) if rng.random() < 0.6 else 0.0)


# --------------------------------------------------------------------------- humanoid geometry


@dataclass(frozen=True)
class _Skeleton:
    """Leg and foot geometry of the humanoid, read from its MuJoCo model (rest pose, metres).

    Attributes:
        hip: (2, 3) left/right hip joint offsets from the pelvis origin, pelvis frame.
        thigh, shank: hip→knee and knee→ankle lengths.
        ankle_height: ankle joint above the sole when the foot is flat.
        heel, toe: foot extent behind/ahead of the ankle joint; half_width: half its width.
        foot_top: top of the foot above the sole.
        toe_joint: (3,) toe joint relative to the ankle joint (the heel-off pivot).
        pelvis_height: pelvis origin above the soles in the rest pose.
        stature: the humanoid's height (m), to compose scene models of the same humanoid.
    """

    hip: np.ndarray
    thigh: float
    shank: float
    ankle_height: float
    heel: float
    toe: float
    half_width: float
    foot_top: float
    toe_joint: np.ndarray
    pelvis_height: float
    stature: float

    @property
    def leg(self) -> float:
        return self.thigh + self.shank

    @classmethod
    def from_model(cls, model: mujoco.MjModel, stature: float) -> _Skeleton:
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        pos = {name: data.xpos[model.body(name).id].copy() for name in BODY_NAMES}
        foot_ids = {model.body("L_Ankle").id, model.body("L_Toe").id}
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for g in range(model.ngeom):
            if model.geom_bodyid[g] in foot_ids:
                lo = np.minimum(lo, data.geom_xpos[g] - model.geom_size[g])
                hi = np.maximum(hi, data.geom_xpos[g] + model.geom_size[g])
        ankle = pos["L_Ankle"]
        return cls(
            hip=np.stack([pos["L_Hip"] - pos["Pelvis"], pos["R_Hip"] - pos["Pelvis"]]),
            thigh=float(np.linalg.norm(pos["L_Knee"] - pos["L_Hip"])),
            shank=float(np.linalg.norm(pos["L_Ankle"] - pos["L_Knee"])),
            ankle_height=float(ankle[2] - lo[2]), heel=float(ankle[0] - lo[0]), toe=float(hi[0] - ankle[0]),
            half_width=float((hi[1] - lo[1]) / 2), foot_top=float(hi[2] - lo[2]),
            toe_joint=pos["L_Toe"] - ankle, pelvis_height=float(pos["Pelvis"][2] - lo[2]), stature=stature)

    def foot_points(self) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) points filling the foot box relative to the ankle joint, and (P,) which of
        them belong to the toe segment (ahead of the toe joint)."""
        xs = np.linspace(-self.heel, self.toe, 13)
        ys = np.linspace(-self.half_width, self.half_width, 4)
        zs = np.linspace(0.0, self.foot_top, 3) - self.ankle_height
        pts = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)
        return pts, pts[:, 0] > self.toe_joint[0]


# --------------------------------------------------------------------------- path and plan


@dataclass(frozen=True)
class _Path:
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
class _Move:
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
class _Plan:
    """Footsteps and pelvis keyframes of a whole clip (mutable while it is being built)."""

    feet: list[tuple[float, float]]  # current (s, z) of the left and right ankle
    moves: list[list[_Move]] = field(default_factory=lambda: [[], []])
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


_PELVIS_AHEAD = 0.04  # m: the standing pelvis is above the mid-foot, ahead of the ankles


def _add_walk(plan: _Plan, t0: float, targets: list[tuple[float, float]], first: int, gait: GaitParams,
              skel: _Skeleton, stand_after: float = 0.6) -> None:
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
        plan.moves[foot].append(_Move(t, t + swing, s_prev, z_prev, s, z, heel=heel, roll=roll))
        landed[foot] = t + swing
        lean = 0.10 if z - z_prev > 0.02 else 0.04
        plan.pose(t + swing / 2, s_o + _PELVIS_AHEAD, _SIDE[other] * gait.sway, z_o + stand + gait.bob, pitch=lean)
        plan.feet[foot] = (s, z)
        t += swing
        if k < len(targets) - 1:
            plan.pose(t + step * gait.double_support / 2, (s + s_o) / 2 + _PELVIS_AHEAD, 0.0,
                      (z + z_o) / 2 + stand - gait.bob, pitch=lean)
            t += step * gait.double_support
    (s_l, z_l), (s_r, z_r) = plan.feet
    plan.end = t + stand_after
    for when in (t + 0.6 * stand_after, plan.end):  # twice, so the motion comes to rest
        plan.pose(when, (s_l + s_r) / 2 + _PELVIS_AHEAD, 0.0, max(z_l, z_r) + stand)
    _balance_pelvis(plan, t0 - _WALK_PREPARATION, feet_before, gait, skel)


_WALK_PREPARATION = 0.3  # s before the first lift in which the body starts to shift over the stance foot
_ZMP_HEEL, _ZMP_TOE = 0.0, 0.08  # m ahead of the ankle: the centre of pressure rolls from heel to toe
_BALANCE_DT = 1.0 / 60.0  # s: the pendulum's time step (keys are written at this rate)
_BALANCE_JERK_WEIGHT = 1e-4  # m of centre-of-pressure error that weigh as much as 1 m/s³ of jerk


def _balance_pelvis(plan: _Plan, start: float, feet: list[float], gait: GaitParams, skel: _Skeleton) -> None:
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
        knots["lat"] += [_SIDE[stance] * gait.step_width / 2] * 2
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


def _fill(a: float, b: float, step: float) -> list[float]:
    """Evenly spaced positions after ``a`` up to and including ``b``, no step longer than ``step``."""
    n = max(1, int(np.ceil((b - a) / step - 1e-9)))
    return [a + (b - a) * i / n for i in range(1, n + 1)]


def _footsteps(anchors: list[tuple[float, float]], start: float, step: float) -> list[tuple[float, float]]:
    """Footstep targets through ``anchors`` ((s, z), in order), filling level stretches evenly,
    ending with the trailing foot placed beside the leading one."""
    targets: list[tuple[float, float]] = []
    s_prev, z_prev = start, anchors[0][1]
    for s, z in anchors:
        if abs(z - z_prev) > 1e-9:
            targets.append((s, z))
        else:
            targets += [(x, z) for x in _fill(s_prev, s, step)]
        s_prev, z_prev = s, z
    targets.append(targets[-1])
    return targets


# Foot placement margins (m): toe or heel to a higher edge, and a foot fully on a level.
_EDGE_MARGIN = 0.02
_LEVEL_MARGIN = 0.04


def _tread_ankle(level: _Level, skel: _Skeleton, higher_before: bool, higher_after: bool) -> float:
    """Ankle x on a level: the foot centred, but kept off the riser of a higher neighbour."""
    x = (level.x0 + level.x1) / 2 - (skel.toe - skel.heel) / 2
    if higher_after:
        x = min(x, level.x1 - _EDGE_MARGIN - skel.toe)
    if higher_before:
        x = max(x, level.x0 + _EDGE_MARGIN + skel.heel)
    return x


def _terrain_anchors(levels: list[_Level], before: float, after: float, skel: _Skeleton,
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


# --------------------------------------------------------------------------- swing arcs


def _min_jerk(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10 - 15 * u + 6 * u**2)


def _window(u: np.ndarray, a: float, b: float) -> np.ndarray:
    return _min_jerk((u - a) / (b - a))


def _swing_profile(move: _Move, u: np.ndarray, lift: float) -> tuple[np.ndarray, np.ndarray]:
    """Arc length and sole height of a swing at phases ``u`` in [0, 1].

    Stepping up, the foot rises before it travels; stepping down, it travels before it drops;
    on the level both go together. ``lift`` is the extra height of the arc at mid-swing.
    """
    dz = move.z1 - move.z0
    if dz > 0.02:
        h, v = _window(u, 0.2, 1.0), _window(u, 0.0, 0.7)
    elif dz < -0.02:
        h, v = _window(u, 0.0, 0.8), _window(u, 0.3, 1.0)
    else:
        h, v = _window(u, 0.0, 1.0), _window(u, 0.0, 1.0)
    return move.s0 + (move.s1 - move.s0) * h, move.z0 + dz * v + lift * np.sin(np.pi * u) ** 2


def _flat_ankle(path: _Path, s: np.ndarray, z: np.ndarray, side: int, gait: GaitParams,
                skel: _Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) ankle joint and (n,) yaw of a flat foot of ``side`` at arc ``s`` on a surface at ``z``."""
    s, z = np.asarray(s, dtype=float), np.asarray(z, dtype=float)
    xy = path.frame(s, np.full_like(s, _SIDE[side] * gait.step_width / 2))
    return np.concatenate([xy, (z + skel.ankle_height)[:, None]], axis=1), path.heading(s) + _SIDE[side] * gait.toe_out


def _pitch_matrix(pitch: np.ndarray) -> np.ndarray:
    return Rotation.from_euler("y", np.asarray(pitch, dtype=float)[:, None]).as_matrix()


def _heel_off(ankle: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, skel: _Skeleton) -> np.ndarray:
    """Ankle of a foot raised by ``pitch`` (heel up) about the toe joint of its flat pose."""
    yaw_m = _rot_z(yaw)
    pivot = ankle + yaw_m @ skel.toe_joint
    return pivot - np.einsum("nij,nj->ni", yaw_m @ _pitch_matrix(pitch), np.broadcast_to(skel.toe_joint, ankle.shape))


def _swing_pose(move: _Move, u: np.ndarray, lift: float, side: int, path: _Path, gait: GaitParams,
                skel: _Skeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ankle (n, 3), yaw, pitch and arc position of a swinging foot at phases ``u``.

    The heel-off pitch and the ankle offset it caused fade out over the first half of the swing.
    """
    s, z = _swing_profile(move, u, lift)
    ankle, yaw = _flat_ankle(path, s, z, side, gait, skel)
    start, yaw0 = _flat_ankle(path, [move.s0], [move.z0], side, gait, skel)
    raised = _heel_off(start, yaw0, np.array([move.heel]), skel)
    fade = 1.0 - _window(u, 0.0, 0.5)
    return ankle + (raised - start) * fade[:, None], yaw, move.heel * fade, s


def _foot_world(ankle: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, skel: _Skeleton) -> np.ndarray:
    """(n, P, 3) world points of the foot: the hind foot pitched, the toe segment kept flat."""
    pts, toe = skel.foot_points()
    yaw_m = _rot_z(yaw)
    foot = yaw_m @ _pitch_matrix(pitch)
    hind = ankle[:, None] + np.einsum("nij,pj->npi", foot, pts)
    toe_origin = ankle + foot @ skel.toe_joint
    front = toe_origin[:, None] + np.einsum("nij,pj->npi", yaw_m, pts - skel.toe_joint)
    return np.where(toe[None, :, None], front, hind)


def _swing_lift(move: _Move, side: int, path: _Path, boxes: list[Box], skel: _Skeleton, gait: GaitParams,
                clearance: float = 0.025) -> float:
    """Smallest arc height (in 1 cm steps from 4 cm) that keeps the swinging foot ``clearance``
    away from every box in mid-swing and out of them everywhere."""
    u = np.linspace(0.0, 1.0, 41)
    need = clearance * np.sin(np.pi * u) ** 2
    for lift in np.arange(0.04, 0.40, 0.01):
        ankle, yaw, pitch, _ = _swing_pose(move, u, lift, side, path, gait, skel)
        world = _foot_world(ankle, yaw, pitch, skel)
        depth = -box_signed_distance(world.reshape(-1, 3), boxes).reshape(len(u), -1).min(axis=1)
        if np.all(depth + need <= 1e-6):
            return float(lift)
    raise RuntimeError(f"no swing arc clears the scene for the step {move}")


# --------------------------------------------------------------------------- IK and assembly


def _rot_z(a: np.ndarray) -> np.ndarray:
    return Rotation.from_euler("z", np.asarray(a)[:, None]).as_matrix()


def _leg_ik(hip: np.ndarray, ankle: np.ndarray, forward: np.ndarray, skel: _Skeleton,
            reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Two-link IK: (T, 3, 3) thigh world rotations and (T,) knee flexion (rad, positive bends).

    The leg plane contains ``forward`` (the knee points that way); the thigh and shank hang
    along -z in the rest pose and the knee hinge is the thigh's y axis.
    """
    l1, l2 = skel.thigh, skel.shank
    d = ankle - hip
    dist = np.clip(np.linalg.norm(d, axis=1), abs(l1 - l2) + 1e-6, reach)
    interior = np.arccos(np.clip((l1**2 + l2**2 - dist**2) / (2 * l1 * l2), -1.0, 1.0))
    knee = np.pi - interior
    local = np.stack([-l2 * np.sin(knee), np.zeros_like(knee), -l1 - l2 * np.cos(knee)], axis=1)

    def frame(axis: np.ndarray, hint: np.ndarray) -> np.ndarray:
        e1 = axis / np.linalg.norm(axis, axis=1, keepdims=True)
        e2 = hint - np.sum(hint * e1, axis=1, keepdims=True) * e1
        e2 /= np.linalg.norm(e2, axis=1, keepdims=True)
        return np.stack([e1, e2, np.cross(e1, e2)], axis=2)

    world = frame(d, forward) @ np.swapaxes(frame(local, np.tile([1.0, 0.0, 0.0], (len(d), 1))), 1, 2)
    return world, knee


def _hinge_angles(local: np.ndarray) -> np.ndarray:
    """(T, J, 3) x-y-z hinge angles of (T, J, 3, 3) leg rotations, on the branch with the smaller
    x (ab/adduction, inversion) angle.

    A hip flexed past 90 degrees is on the second Euler branch (x + pi, pi - y, z + pi); choosing by
    the smaller x instead of by closeness to the previous frame stays correct through the
    near-singular frames of sitting down, where the frame-to-frame choice can lock onto the
    wrong branch.
    """
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    first = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_euler("XYZ").reshape(local.shape[:-2] + (3,))
    second = wrap(first + np.array([np.pi, 0.0, np.pi]))
    second[..., 1] = wrap(np.pi - first[..., 1])
    angles = np.where((np.abs(second[..., 0]) < np.abs(first[..., 0]))[..., None], second, first)
    return np.unwrap(angles, axis=0)


def _root_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    return Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()


def _dof(name: str) -> int:
    return DOF_NAMES.index(name)


@dataclass
class _Frames:
    """Per-frame targets that the IK turns into a motion."""

    pelvis_xy: np.ndarray  # (T, 2)
    pelvis_z: np.ndarray  # (T,)
    yaw: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray
    spine: np.ndarray  # trunk flexion above the pelvis (rad, forward positive)
    arms: np.ndarray  # extra shoulder flexion (rad)
    ankle: np.ndarray  # (T, 2, 3) ankle targets
    foot_yaw: np.ndarray  # (T, 2)
    foot_pitch: np.ndarray  # (T, 2) heel-off pitch (rad, heel up positive)
    foot_s: np.ndarray  # (T, 2) arc positions of the ankles (for the arm swing)
    pelvis_s: np.ndarray  # (T,)
    stance: np.ndarray  # (T, 2) bool
    phase: np.ndarray  # (T, 2) swing phase in [0, 1] (0 in stance)


def _hips(frames: _Frames, skel: _Skeleton) -> tuple[np.ndarray, np.ndarray]:
    rot = _root_rotation(frames.yaw, frames.pitch, frames.roll)
    pelvis = np.concatenate([frames.pelvis_xy, frames.pelvis_z[:, None]], axis=1)
    return rot, pelvis[:, None, :] + np.einsum("tij,lj->tli", rot, skel.hip)


def _limit_pelvis_height(frames: _Frames, skel: _Skeleton, reach: float, fps: float) -> None:
    """Lower the pelvis where a leg could not reach its foot, keeping the height smooth."""
    rot, hips = _hips(frames, skel)
    horizontal = np.linalg.norm(hips[..., :2] - frames.ankle[..., :2], axis=2)
    drop = hips[..., 2] - frames.pelvis_z[:, None]
    limit = frames.ankle[..., 2] + np.sqrt(np.maximum(reach**2 - horizontal**2, 0.0)) - drop
    # A swinging leg shortens itself by flexing; it only has to reach near lift-off and landing.
    free = ~frames.stance & (frames.phase > 0.1) & (frames.phase < 0.85)
    limit = np.where(free, np.inf, limit).min(axis=1)
    frames.pelvis_z = _smooth_below(frames.pelvis_z, limit, fps)


_HEIGHT_ACCEL_WEIGHT = 0.03  # m of height error that weigh as much as 1 m/s² of vertical acceleration
_HEIGHT_KEPT_WEIGHT = 100.0  # weight of the planned height, relative, where the legs are far from straight


def _smooth_below(z: np.ndarray, limit: np.ndarray, fps: float) -> np.ndarray:
    """The height closest to ``z`` with small vertical accelerations that stays under ``limit``
    (bounded least squares). Where the legs are far from straight (a seated pelvis) the planned
    height weighs :data:`_HEIGHT_KEPT_WEIGHT` times more, so that it stays on its seat.

    Clipping to the limit alone dipped the pelvis by up to 10 cm within a few frames at each
    double support: vertical accelerations near ±g that no leg force produces.
    """
    n = len(z)
    if n < 3:
        return np.minimum(z, limit)
    accel = np.zeros((n - 2, n))
    rows = np.arange(n - 2)
    accel[rows, rows], accel[rows, rows + 1], accel[rows, rows + 2] = 1.0, -2.0, 1.0
    slack = np.clip((limit - z - 0.1) / 0.1, 0.0, 1.0)  # 0 up to 10 cm under the reach, 1 from 20 cm
    weight = 1.0 + (_HEIGHT_KEPT_WEIGHT - 1.0) * slack
    matrix = np.vstack([np.diag(weight), _HEIGHT_ACCEL_WEIGHT * fps**2 * accel])
    return lsq_linear(matrix, np.concatenate([weight * z, np.zeros(n - 2)]), bounds=(-np.inf, limit),
                      method="bvls").x


def _solve(frames: _Frames, skel: _Skeleton, gait: GaitParams, fps: float, reach: float) -> Motion:
    """Joint angles for the per-frame targets: legs by IK, the rest from the trunk/arm channels."""
    t = len(frames.pelvis_z)
    rot, hips = _hips(frames, skel)
    foot_rot = np.stack([_rot_z(frames.foot_yaw[:, i]) @ _pitch_matrix(frames.foot_pitch[:, i])
                         for i in range(2)], axis=1)
    heading = np.stack([np.cos(frames.yaw), np.sin(frames.yaw), np.zeros(t)], axis=1)
    dof = np.zeros((t, len(DOF_NAMES)))
    local = np.empty((t, 4, 3, 3))
    knees, shanks = [], []
    for leg in range(2):
        toward = foot_rot[:, leg, :, 0] + heading
        thigh, knee = _leg_ik(hips[:, leg], frames.ankle[:, leg], toward, skel, reach)
        shanks.append(thigh @ Rotation.from_euler("y", knee[:, None]).as_matrix())
        local[:, 2 * leg] = np.swapaxes(rot, 1, 2) @ thigh
        local[:, 2 * leg + 1] = np.swapaxes(shanks[leg], 1, 2) @ foot_rot[:, leg]
        knees.append(knee)
    angles = _hinge_angles(local)
    # A swinging foot tucked behind the body points its toes down instead of staying flat
    # (the leg IK does not depend on the foot's orientation, so only the ankle changes).
    for leg in range(2):
        extra = np.maximum(_SWING_DORSIFLEXION - angles[:, 2 * leg + 1, 1], 0.0)
        # Smoothly, and flat again before landing so the toes cannot catch the next surface.
        u = frames.phase[:, leg]
        fade = np.where(frames.stance[:, leg], 0.0, _window(u, 0.0, 0.2) * (1.0 - _window(u, 0.45, 0.8)))
        extra = gaussian_filter1d(maximum_filter1d(extra * fade, 5), 1.0) * fade
        local[:, 2 * leg + 1] = local[:, 2 * leg + 1] @ _pitch_matrix(extra)
    angles = _hinge_angles(local)
    for leg, side in enumerate("LR"):
        for axis_index, axis in enumerate("xyz"):
            dof[:, _dof(f"{side}_Hip_{axis}")] = angles[:, 2 * leg, axis_index]
            dof[:, _dof(f"{side}_Ankle_{axis}")] = angles[:, 2 * leg + 1, axis_index]
        dof[:, _dof(f"{side}_Knee_y")] = knees[leg]
        dof[:, _dof(f"{side}_Toe_y")] = -frames.foot_pitch[:, leg]  # the toe stays flat

    # Trunk: lean spread over three joints, counter-rotation against the pelvis yaw oscillation,
    # head kept level; arms hang 75 degrees down and swing against the legs.
    path_yaw = frames.yaw - _pelvis_twist(frames)
    for name in ("Torso", "Spine", "Chest"):
        dof[:, _dof(f"{name}_y")] = frames.spine / 3
        dof[:, _dof(f"{name}_z")] = -(frames.yaw - path_yaw) / 3
        dof[:, _dof(f"{name}_x")] = -frames.roll / 3
    dof[:, _dof("Neck_y")] = -(frames.pitch + frames.spine) * 0.5
    dof[:, _dof("Head_y")] = -(frames.pitch + frames.spine) * 0.5
    lead = frames.foot_s - frames.pelvis_s[:, None]
    for leg, side in enumerate("LR"):
        sign = _SIDE[leg]
        swing = -gait.arm_swing * lead[:, leg] + frames.arms  # forward positive
        dof[:, _dof(f"{side}_Shoulder_x")] = -sign * np.deg2rad(75.0)
        dof[:, _dof(f"{side}_Shoulder_z")] = -sign * swing
        dof[:, _dof(f"{side}_Elbow_z")] = -sign * np.deg2rad(8.0)

    pelvis = np.concatenate([frames.pelvis_xy, frames.pelvis_z[:, None]], axis=1)
    quat = Rotation.from_matrix(rot).as_quat(scalar_first=True)
    quat *= np.where(quat[:, :1] < 0, -1.0, 1.0)
    return Motion(fps=fps, root_pos=pelvis, root_quat=quat, dof_pos=dof)


def _pelvis_twist(frames: _Frames) -> np.ndarray:
    """Pelvis yaw oscillation of gait: the swing-side hip comes forward with its foot."""
    return -0.12 * (frames.foot_s[:, _L] - frames.foot_s[:, _R])


def _evaluate(plan: _Plan, path: _Path, boxes: list[Box], skel: _Skeleton, gait: GaitParams,
              fps: float) -> _Frames:
    """Sample the plan at ``fps``: pelvis channels, stance holds, heel-offs and swing arcs."""
    t = np.arange(int(round(plan.end * fps)) + 1) / fps
    n = len(t)
    ankle, foot_yaw = np.empty((n, 2, 3)), np.empty((n, 2))
    foot_pitch, foot_s = np.zeros((n, 2)), np.empty((n, 2))
    stance = np.ones((n, 2), dtype=bool)
    phase = np.zeros((n, 2))
    for foot in range(2):
        moves = plan.moves[foot]
        s_hold = np.full(n, moves[0].s0 if moves else plan.feet[foot][0])
        z_hold = np.full(n, moves[0].z0 if moves else plan.feet[foot][1])
        for move in moves:
            after = t >= move.land
            s_hold[after], z_hold[after] = move.s1, move.z1
        ankle[:, foot], foot_yaw[:, foot] = _flat_ankle(path, s_hold, z_hold, foot, gait, skel)
        foot_s[:, foot] = s_hold
        for move in moves:
            rolling = (t >= move.lift - move.roll) & (t <= move.lift)
            if rolling.any() and move.roll > 0:
                pitch = move.heel * _min_jerk((t[rolling] - move.lift + move.roll) / move.roll)
                ankle[rolling, foot] = _heel_off(ankle[rolling, foot], foot_yaw[rolling, foot], pitch, skel)
                foot_pitch[rolling, foot] = pitch
            inside = (t > move.lift) & (t < move.land)
            if not inside.any():
                continue
            lift = _swing_lift(move, foot, path, boxes, skel, gait)
            u = (t[inside] - move.lift) / (move.land - move.lift)
            (ankle[inside, foot], foot_yaw[inside, foot], foot_pitch[inside, foot],
             foot_s[inside, foot]) = _swing_pose(move, u, lift, foot, path, gait, skel)
            stance[inside, foot] = False
            phase[inside, foot] = u
    pelvis_s, lat = plan.channel("s", t), plan.channel("lat", t)
    frames = _Frames(
        pelvis_xy=path.frame(pelvis_s, lat), pelvis_z=plan.channel("z", t), yaw=path.heading(pelvis_s),
        pitch=plan.channel("pitch", t), roll=0.8 * lat, spine=plan.channel("spine", t),
        arms=plan.channel("arms", t), ankle=ankle, foot_yaw=foot_yaw, foot_pitch=foot_pitch,
        foot_s=foot_s, pelvis_s=pelvis_s, stance=stance, phase=phase)
    frames.yaw = frames.yaw + _pelvis_twist(frames)
    return frames


_SWING_DORSIFLEXION = np.deg2rad(-40.0)  # most a swinging ankle flexes before the toes drop
_REACH = 0.995  # fraction of the full leg length a stance leg may extend to (knee ~11 deg)


def _to_motion(frames: _Frames, skel: _Skeleton, gait: GaitParams, fps: float, model: mujoco.MjModel,
               boxes: list[Box]) -> Motion:
    """IK, then checks on the real model: where a stance ankle misses its target the pelvis is
    lowered, and where a swinging foot (its toes dropped by the IK) touches the scene its arc
    is raised; both are redone until neither happens."""
    _limit_pelvis_height(frames, skel, _REACH * skel.leg, fps)
    scene = scene_model(boxes, skel.stature)
    feet = [[scene.body(b).id for b in bodies] for bodies in _STANCE_BODIES]
    data = mujoco.MjData(scene)
    for _ in range(8):
        motion = _solve(frames, skel, gait, fps, skel.leg * 0.9999)
        ankles = compute_kinematics(motion, model).body_pos[:, [BODY_NAMES.index("L_Ankle"),
                                                             BODY_NAMES.index("R_Ankle")]]
        miss = np.where(frames.stance, np.linalg.norm(ankles - frames.ankle, axis=2), 0.0).max(axis=1)
        depth = _swing_penetration(motion, frames, scene, data, feet)
        if miss.max() < 1e-4 and depth.max() < 1e-4:
            return motion
        frames.pelvis_z = frames.pelvis_z - gaussian_filter1d(maximum_filter1d(miss, 9), 2.0) * 1.5
        raise_by = gaussian_filter1d(maximum_filter1d(depth + 0.005 * (depth > 0), 9, axis=0), 2.0, axis=0)
        frames.ankle[..., 2] += raise_by * np.sin(np.pi * frames.phase) * ~frames.stance
    raise RuntimeError(f"the legs cannot reach the planned footholds (miss {miss.max():.4f} m) or the "
                       f"swinging feet cannot clear the scene (depth {depth.max():.4f} m)")


def _swing_penetration(motion: Motion, frames: _Frames, scene: mujoco.MjModel, data: mujoco.MjData,
                       feet: list[list[int]]) -> np.ndarray:
    """(T, 2) deepest penetration of each swinging foot into the scene."""
    depth = np.zeros((motion.num_frames, 2))
    qpos = motion.qpos()
    for k in np.flatnonzero(~frames.stance.all(axis=1)):
        data.qpos[:] = qpos[k]
        mujoco.mj_kinematics(scene, data)
        mujoco.mj_collision(scene, data)
        for c in data.contact[:data.ncon]:
            bodies = {scene.geom_bodyid[c.geom1], scene.geom_bodyid[c.geom2]}
            for leg in range(2):
                if not frames.stance[k, leg] and bodies & set(feet[leg]):
                    depth[k, leg] = max(depth[k, leg], -c.dist)
    return depth


# --------------------------------------------------------------------------- sitting


def _seated_height(seat: SeatParams, feet_s: float, pelvis_s: float, pitch: float, gait: GaitParams,
                   skel: _Skeleton) -> float:
    """Pelvis height at which the thighs rest on the seat (1 mm compression), by bisection on
    the real humanoid geometry posed by the same IK as the motion."""
    seat_model, seat_geom = _seat_model(seat, skel.stature)
    thighs = [seat_model.geom(g).id for g in range(seat_model.ngeom)
              if seat_model.geom_bodyid[g] in {seat_model.body("L_Hip").id, seat_model.body("R_Hip").id,
                                               seat_model.body("Pelvis").id}]
    data = mujoco.MjData(seat_model)

    def gap(z: float) -> float:
        frames = _standing_frames(np.full(2, pelvis_s), np.full(2, z), np.full(2, pitch), feet_s, gait, skel)
        motion = _solve(frames, skel, gait, 30.0, skel.leg * 0.9999)
        data.qpos[:] = motion.qpos()[0]
        mujoco.mj_kinematics(seat_model, data)
        return min(mujoco.mj_geomDistance(seat_model, data, g, seat_geom, 0.5, None) for g in thighs)

    # Scan up from the seat (the gap is not monotonic far above it, where the straightening
    # legs swing the knees back into the seat's front), then bisect to the touching height.
    lo = seat.height
    for hi in seat.height + np.arange(0.05, 0.40, 0.01):
        if gap(hi) >= -0.001:
            break
        lo = hi
    else:
        raise RuntimeError(f"found no seated pose on a {seat.height:.2f} m seat for this humanoid")
    for _ in range(30):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if gap(mid) < -0.001 else (lo, mid)
    return hi


def _seat_model(seat: SeatParams, stature: float) -> tuple[mujoco.MjModel, int]:
    """The humanoid with the seat box alone, and the seat's geom id."""
    model = scene_model([b for b in seat_boxes(seat) if b.name == "seat"], stature)
    return model, model.geom("seat").id


def _standing_frames(pelvis_s: np.ndarray, pelvis_z: np.ndarray, pitch: np.ndarray, feet_s: float,
                     gait: GaitParams, skel: _Skeleton, spine: float = 0.0, arms: float = 0.0) -> _Frames:
    """Frames with both feet planted at ``feet_s`` on the floor of a straight path."""
    n = len(pelvis_s)
    zeros = np.zeros(n)
    ankle = np.zeros((n, 2, 3))
    ankle[..., 0] = feet_s
    ankle[..., 1] = _SIDE * gait.step_width / 2
    ankle[..., 2] = skel.ankle_height
    return _Frames(pelvis_xy=np.stack([pelvis_s, zeros], axis=1), pelvis_z=pelvis_z, yaw=zeros, pitch=pitch,
                   roll=zeros, spine=np.full(n, spine), arms=np.full(n, arms), ankle=ankle,
                   foot_yaw=np.tile(_SIDE * gait.toe_out, (n, 1)), foot_pitch=np.zeros((n, 2)),
                   foot_s=np.full((n, 2), feet_s),
                   pelvis_s=pelvis_s, stance=np.ones((n, 2), dtype=bool), phase=np.zeros((n, 2)))


def _add_sit(plan: _Plan, seat: SeatParams, gait: GaitParams, skel: _Skeleton, rng: np.random.Generator) -> float:
    """Stand, sit down on the seat behind, stay, stand up; feet planted at s = 0. Returns the end time.

    The trunk's forward lean comes from the spine while the pelvis tilts back (as it does when
    sitting): this keeps the hips' flexion below 90 degrees, where their x-y-z hinges are
    singular and ab/adduction would swing wildly.

    The body lowers itself onto, stays on, and rises from the front of the seat, where under
    the lean the centre of mass is just behind the heels (:func:`_perched_position`,
    :data:`_RISE_COM_MARGIN`; the pelvis already moves forward as the thighs leave the seat).
    Sitting straight back onto the seat and rising from it put the centre of mass 9-10 cm
    behind the heels (the first generator): no ground force lowers or lifts a body from there
    without it falling. Perching further forward hides the seat from the kinematic contact cue,
    which needs the seated centre of mass clearly behind the feet (docs/synthetic_clips.md).
    Sliding back on the seat and forward again before rising (the second) asked a simulated
    body to scoot 15 cm along a seat that holds it by friction: policies learned to skip the
    slide, and from a seated start they could not rise.
    """
    stand = skel.pelvis_height - 0.012
    seated_pitch = -0.2
    down, hold, up = rng.uniform(1.4, 1.8), rng.uniform(1.2, 1.8), rng.uniform(1.4, 1.8)
    lean_down, lean_up = rng.uniform(1.05, 1.2), rng.uniform(1.05, 1.2)
    t1 = 0.6
    t2, t3 = t1 + down, t1 + down + hold
    t4 = t3 + up
    # The least lean needs the pelvis furthest forward; the other lean is then over the feet too.
    seated_s, z_seat = _perched_position(seat, seated_pitch, min(lean_down, lean_up), gait, skel)
    plan.pose(0.0, _PELVIS_AHEAD, 0.0, stand)
    plan.pose(t1, _PELVIS_AHEAD, 0.0, stand)
    # Down: lean, lower onto the seat's front, then sit up.
    touch = t1 + (1.0 - _SEAT_OFF_SHARE) * down
    plan.key("spine", t1 + 0.6 * (touch - t1), lean_down)
    plan.key("arms", t1 + 0.6 * (touch - t1), 0.6 * lean_down)
    plan.pose(touch, seated_s, 0.0, z_seat, pitch=seated_pitch, spine=lean_down, arms=0.6 * lean_down)
    plan.pose(t2, seated_s, 0.0, z_seat, pitch=seated_pitch, spine=_SEATED_SPINE)
    plan.pose(t3, seated_s, 0.0, z_seat, pitch=seated_pitch, spine=_SEATED_SPINE)
    # Up: lean forward on the seat, then rise while moving forward.
    seat_off = t3 + _SEAT_OFF_SHARE * up
    plan.pose(seat_off, seated_s, 0.0, z_seat, pitch=seated_pitch, spine=lean_up, arms=0.6 * lean_up)
    plan.pose(t4, _PELVIS_AHEAD, 0.0, stand)
    return t4


def _perched_position(seat: SeatParams, pitch: float, lean: float, gait: GaitParams,
                      skel: _Skeleton) -> tuple[float, float]:
    """The pelvis (s, z) on the seat from which the body can rise (and onto which it can lower
    itself) with the spine leaning by ``lean``.

    The first position forward (1 cm steps, the pelvis kept :data:`_SEAT_EDGE_CLEARANCE` behind
    the seat's front) that puts the centre of mass :data:`_RISE_COM_MARGIN` in front of the heels.
    """
    model, _ = _seat_model(seat, skel.stature)
    data = mujoco.MjData(model)
    feet = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX
            and model.body(model.geom_bodyid[g]).name in FEET]
    for pelvis_s in np.arange(seat.front - _PERCH_SCAN_DEPTH, seat.front - _SEAT_EDGE_CLEARANCE + 1e-9, 0.01):
        z = _seated_height(seat, 0.0, pelvis_s, pitch, gait, skel)
        frames = _standing_frames(np.full(2, pelvis_s), np.full(2, z), np.full(2, pitch), 0.0, gait, skel,
                                  spine=lean, arms=0.6 * lean)
        data.qpos[:] = _solve(frames, skel, gait, 30.0, skel.leg * 0.9999).qpos()[0]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        heels = min((data.geom_xpos[g] - np.abs(data.geom_xmat[g].reshape(3, 3)) @ model.geom_size[g])[0]
                    for g in feet)
        if data.subtree_com[model.body("Pelvis").id][0] - heels >= _RISE_COM_MARGIN:
            return float(pelvis_s), z
    raise RuntimeError(f"no pelvis position on this seat (front at {seat.front:.2f} m) puts the centre of "
                       f"mass over the feet")


def _seat_contacts(motion: Motion, boxes: list[Box], stature: float) -> np.ndarray:
    """(T,) frames where the thighs are within :data:`_SEAT_CONTACT_TOLERANCE` of the seat."""
    model = scene_model([b for b in boxes if b.name == "seat"], stature)
    data = mujoco.MjData(model)
    seat = model.geom("seat").id
    thighs = [g for g in range(model.ngeom)
              if model.geom_bodyid[g] in {model.body("L_Hip").id, model.body("R_Hip").id}]
    qpos = motion.qpos()
    out = np.zeros(motion.num_frames, dtype=bool)
    for k in range(motion.num_frames):
        data.qpos[:] = qpos[k]
        mujoco.mj_kinematics(model, data)
        out[k] = min(mujoco.mj_geomDistance(model, data, g, seat, 0.1, None) for g in thighs) \
            < _SEAT_CONTACT_TOLERANCE
    return out


# --------------------------------------------------------------------------- clips


@dataclass(frozen=True)
class SynthConfig:
    """Settings shared by all kinds.

    Attributes:
        fps: frame rate of the generated motion (the paper's policy rate).
        height: stature of the humanoid the motion is generated for (m).
    """

    fps: float = 30.0
    height: float = 1.70


def make_clip(kind: str, seed: int, config: SynthConfig | None = None) -> tuple[list[Box], Motion, dict]:
    """A synthetic clip of ``kind`` (one of :data:`KINDS`), deterministic for ``seed``.

    Returns the scene's boxes (the floor first, its top at z = 0), the motion with ground-truth
    ``contacts`` (feet in stance; pelvis and thighs while seated) and a meta dict with
    ``source: "synthetic"``, the kind, the seed and every randomised parameter.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown synthetic clip kind {kind!r}; expected one of {KINDS}")
    cfg = config or SynthConfig()
    rng = np.random.default_rng([int(seed), KINDS.index(kind)])
    model = build_humanoid(HumanoidConfig(height=cfg.height))
    skel = _Skeleton.from_model(model, cfg.height)
    gait = sample_gait(rng, curved=kind == "flat_walk")
    path = _Path(gait.curvature)
    plan = _Plan(feet=[(0.0, 0.0), (0.0, 0.0)])
    first = int(rng.integers(2))
    scene: dict = {}
    if kind == "flat_walk":
        boxes = [floor_box()]
        n = int(rng.integers(7, 10))
        plan.pose(0.0, _PELVIS_AHEAD, 0.0, skel.pelvis_height - 0.012)
        targets = [(gait.step_length * (k - 0.5), 0.0) for k in range(1, n + 1)]
        _add_walk(plan, 0.5, targets + [targets[-1]], first, gait, skel)
    elif kind in ("stairs_up", "stairs_down", "platform_step"):
        if kind == "platform_step":
            params = sample_platform_params(rng)
            boxes = platform_boxes(params)
            levels = [_Level(params.start, params.start + params.length, params.height)]
            start_z = 0.0
            scene = {"platform": asdict(params)}
        else:
            descending = kind == "stairs_down"
            params = sample_stairs_params(rng, descending)
            boxes = stairs_boxes(params, descending)
            levels = _stairs_levels(params, descending)
            start_z = params.top if descending else 0.0
            if descending:  # the walk starts on the landing
                levels = levels[1:]
            scene = {"stairs": asdict(params), "direction": "down" if descending else "up"}
        plan.feet = [(0.0, start_z), (0.0, start_z)]
        plan.pose(0.0, _PELVIS_AHEAD, 0.0, start_z + skel.pelvis_height - 0.012)
        anchors = _terrain_anchors(levels, start_z, 0.0, skel, kind == "stairs_up", gait.step_length)
        _add_walk(plan, 0.5, _footsteps(anchors, 0.0, gait.step_length), first, gait, skel)
    else:  # chair_sit
        params = sample_seat_params(rng)
        # Seat heights are for a 1.70 m adult; scale them with the humanoid's stature.
        params = replace(params, height=round(params.height * cfg.height / 1.70, 3))
        boxes = seat_boxes(params)
        scene = {"seat": asdict(params)}
        t_up = _add_sit(plan, params, gait, skel, rng)
        away = float(rng.uniform(1.2, 1.8))
        targets = [(s, 0.0) for s in _fill(0.0, away, gait.step_length)]
        _add_walk(plan, t_up + 0.3, targets + [targets[-1]], first, gait, skel)
    frames = _evaluate(plan, path, boxes, skel, gait, cfg.fps)
    motion = _to_motion(frames, skel, gait, cfg.fps, model, boxes)
    contacts = np.zeros((motion.num_frames, len(BODY_NAMES)), dtype=bool)
    soles = sole_points(model, motion.qpos(), FEET)
    supported = np.nan_to_num(np.abs(support_tops(soles.reshape(-1, 3)[:, :2], boxes)
                                     - soles.reshape(-1, 3)[:, 2:3]), nan=np.inf).min(axis=1)
    supported = supported.reshape(soles.shape[:2]) < _SUPPORT_TOLERANCE
    for leg, bodies in enumerate(_STANCE_BODIES):
        for body in bodies:  # a toe hanging over a nosing bears no weight
            contacts[:, BODY_NAMES.index(body)] = frames.stance[:, leg] & supported[:, FEET.index(body)]
    if kind == "chair_sit":
        seated = _seat_contacts(motion, boxes, cfg.height)
        for body in _SEAT_BODIES:
            contacts[:, BODY_NAMES.index(body)] = seated
    motion = Motion(fps=motion.fps, root_pos=motion.root_pos, root_quat=motion.root_quat,
                    dof_pos=motion.dof_pos, contacts=contacts)
    _check_ranges(motion)
    meta = {"source": "synthetic", "kind": kind, "seed": int(seed), "scene": scene, "gait": asdict(gait),
            "humanoid_height": cfg.height, "duration_s": motion.duration,
            "generator": "crisp_gym.reconstruct.synth.make_clip"}
    return boxes, motion, meta


def _check_ranges(motion: Motion) -> None:
    """Every hinge within the humanoid's range (a generator bug otherwise)."""
    for i, name in enumerate(DOF_NAMES):
        body, axis = name.rsplit("_", 1)
        lo, hi = np.deg2rad(joint_range_deg(body)["xyz".index(axis)])
        values = motion.dof_pos[:, i]
        if values.min() < lo - 1e-6 or values.max() > hi + 1e-6:
            raise RuntimeError(f"hinge {name} leaves its range [{np.rad2deg(lo):.0f}, {np.rad2deg(hi):.0f}] "
                               f"deg: {np.rad2deg(values.min()):.1f}..{np.rad2deg(values.max()):.1f}")


def bundle_clips(out_dir: Path = CLIPS_DIR, registry: Path = REGISTRY) -> dict[str, Path]:
    """Write the bundled clips (:data:`BUNDLED`) and (re)write the bundled ``registry.yaml``.

    Paths in the registry are relative to the registry file. Returns name -> clip directory.
    """
    out_dir, registry = Path(out_dir), Path(registry)
    written = {}
    for name, (kind, seed) in BUNDLED.items():
        boxes, motion, meta = make_clip(kind, seed)
        written[name] = write_clip(out_dir / name, boxes, motion, {**meta, "name": name}, overwrite=True)
    entries = {}
    for name, path in written.items():
        rel = Path(path).resolve().relative_to(registry.resolve().parent) \
            if Path(path).resolve().is_relative_to(registry.resolve().parent) else Path(path).resolve()
        entries[name] = {"path": rel.as_posix(), "tags": TAGS[name]}
    write_text(registry, "# Bundled clips, written by `crisp synth-clips`.\n"
               + yaml.safe_dump({"clips": entries}, sort_keys=True))
    return written


def main(argv: list[str] | None = None) -> int:
    """Command line: regenerate the bundled clips and registry, or (``--kind``) generate one more
    clip of a kind and seed and register it in the user registry."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=None,
                        help="where the clip directories go (default: assets/clips, or the user clips folder with --kind)")
    parser.add_argument("--registry", type=Path, default=REGISTRY, help="registry file to (re)write (bundled clips)")
    parser.add_argument("--kind", choices=KINDS, help="generate one clip of this kind instead of the bundled set")
    parser.add_argument("--seed", type=int, default=0, help="with --kind: the generator's seed")
    parser.add_argument("--name", help="with --kind: the registered name (default: KIND_sSEED)")
    parser.add_argument("--overwrite", action="store_true", help="with --kind: replace an existing clip")
    args = parser.parse_args(argv)
    if args.kind is None:
        for name, path in bundle_clips(args.out_dir or CLIPS_DIR, args.registry).items():
            print(f"{name}: {path}")
        print(f"registry: {args.registry}")
        return 0
    from crisp_gym.registry import check_clip_name, register_clip, user_clips_dir

    name = check_clip_name(args.name or f"{args.kind}_s{args.seed}")
    out = (args.out_dir or user_clips_dir()) / name
    boxes, motion, meta = make_clip(args.kind, args.seed)
    write_clip(out, boxes, motion, {**meta, "name": name}, overwrite=args.overwrite)  # errors: crisp_gym.cli
    registry = register_clip(name, out, tags=["synthetic", "generated", args.kind])
    print(f"wrote clip '{name}' ({args.kind}, seed {args.seed}, {motion.num_frames} frames) to {out}\n"
          f"registered in {registry}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
