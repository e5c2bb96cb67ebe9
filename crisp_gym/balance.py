"""Can a body balance on its feet while it follows a motion? The centre of pressure it needs.

A reference's accelerations fix the external force and moment the ground must supply
(inverse dynamics of the humanoid with its root free). The ground can only push, and only
through the feet that touch it, so that wrench has to act at a point inside the feet's support
polygon: the centre of pressure (the zero-moment point of legged robotics). Where the motion
asks for one outside the polygon, no controller can follow it without falling or stepping
away; a tracking policy either learns to deviate or fails there. This is why synthetic
references are planned so that it stays inside, and it says how followable an imported clip is.

:func:`followability` sums this up for a whole motion (what ``crisp import-motion`` reports):
how often the centre of pressure leaves the planted feet, how often no foot is down while the
ground must carry the body, and the frame spans where either happens.

All positions are in metres, in the world frame of the motion; frames are the motion's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import mujoco
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from crisp_gym.humanoid import BODY_NAMES, FEET, HumanoidConfig, build_humanoid
from crisp_gym.motion import PLANT_TOLERANCE, Motion, lower_feet, side_sole_heights

GRAVITY = 9.81


def distance_outside_hull(points_xy: np.ndarray, p: np.ndarray) -> float:
    """How far ``p`` lies outside the convex hull of ``points_xy`` (negative inside: minus the
    distance to the nearest edge); ``inf`` when the points span no area."""
    if len(points_xy) < 3:
        return float("inf")
    try:
        hull = ConvexHull(points_xy)
    except QhullError:
        return float("inf")
    return float(np.max(hull.equations[:, :2] @ p + hull.equations[:, 2]))


@dataclass(frozen=True)
class Balance:
    """The centre of pressure a motion needs, per frame (:func:`motion_balance`).

    Attributes:
        cop: (T, 2) xy where the ground's wrench must act, on the plane of the lowest sole
            in contact (NaN where no foot is).
        vertical_force: (T,) the ground's vertical force over body weight (1 standing still;
            below 0 the motion falls faster than gravity).
        outside: (T,) distance of ``cop`` outside the support polygon of the soles in contact
            (negative inside); NaN on frames that are not judged: no foot in contact, or
            another body (a seated pelvis, a hand) also bearing weight.
    """

    cop: np.ndarray
    vertical_force: np.ndarray
    outside: np.ndarray

    def share_outside(self, margin: float) -> float:
        """Share of the judged frames whose centre of pressure is more than ``margin`` m outside."""
        judged = self.outside[np.isfinite(self.outside)]
        return float((judged > margin).mean()) if len(judged) else 0.0


def motion_balance(motion: Motion, stature: float = 1.70) -> Balance:
    """The centre of pressure ``motion`` needs on the humanoid of ``stature`` (see the module
    docstring). ``motion.contacts`` says which feet touch the ground; without contacts every
    frame counts both feet as planted.

    Velocities and accelerations are central differences of the motion (its first and last
    frames repeat their neighbours'). Stepping between levels (stairs) puts the soles at
    different heights; the centre of pressure is then taken on the lower one's plane.
    """
    model = build_humanoid(HumanoidConfig(height=stature))
    data = mujoco.MjData(model)
    motion = motion.in_humanoid_order()
    qpos, qvel = motion.qpos(), motion.qvel()
    qacc = np.gradient(qvel, 1.0 / motion.fps, axis=0)
    soles = _sole_boxes(model)
    feet = list(soles)
    contacts = motion.contacts
    if contacts is None:
        contacts = np.zeros((motion.num_frames, len(BODY_NAMES)), dtype=bool)
        contacts[:, feet] = True
    others = [i for i in range(len(BODY_NAMES)) if i not in feet]
    root = model.body(BODY_NAMES[0]).id
    weight = float(model.body_subtreemass[root]) * GRAVITY

    t = motion.num_frames
    cop, outside, vertical = np.full((t, 2), np.nan), np.full(t, np.nan), np.zeros(t)
    for k in range(t):
        data.qpos[:], data.qvel[:], data.qacc[:] = qpos[k], qvel[k], qacc[k]
        mujoco.mj_inverse(model, data)
        force = data.qfrc_inverse[:3]  # world frame (free joint's linear dofs)
        moment = data.xmat[root].reshape(3, 3) @ data.qfrc_inverse[3:6]  # about the root, world frame
        vertical[k] = force[2] / weight
        touching = [i for i in feet if contacts[k, i]]
        if not touching or force[2] <= 0:
            continue
        points = np.concatenate([_sole_corners(model, data, soles[i]) for i in touching])
        ground = points[:, 2].min()
        # The wrench (force, moment about the root) acts at p on z = ground where its horizontal
        # moment vanishes: moment + (root - p) x force has zero x and y components.
        arm_z = data.xpos[root, 2] - ground
        arm_x = (moment[1] + arm_z * force[0]) / force[2]
        arm_y = (arm_z * force[1] - moment[0]) / force[2]
        cop[k] = data.xpos[root, :2] - (arm_x, arm_y)
        if not contacts[k, others].any():
            outside[k] = distance_outside_hull(points[:, :2], cop[k])
    return Balance(cop=cop, vertical_force=vertical, outside=outside)


@dataclass(frozen=True)
class Followability:
    """How much of a motion a body can balance through on its own feet (:func:`followability`).

    Attributes:
        outside: share of the judged frames whose centre of pressure lies more than ``margin``
            outside the feet in contact.
        unsupported: share of all frames on which nothing touches the ground while the ground
            has to carry more than ``min_support`` of the body's weight (a foot that slides or
            hovers where the motion stands on it).
        spans: ``(first, end)`` frame ranges (``end`` excluded) where either happens.
        margin: m, the threshold of ``outside``.
        min_support: body weights, the threshold of ``unsupported``.
    """

    outside: float
    unsupported: float
    spans: tuple[tuple[int, int], ...]
    margin: float
    min_support: float

    def describe(self, max_spans: int = 6) -> str:
        """One line for the user."""
        head = (f"balance: centre of pressure over {100 * self.margin:.0f} cm outside the feet on "
                f"{100 * self.outside:.0f} % of judged frames, no foot down under load on "
                f"{100 * self.unsupported:.0f} %")
        if not self.spans:
            return head + " (a body can follow it on its feet)"
        shown = ", ".join(f"{a}-{b - 1}" for a, b in self.spans[:max_spans])
        more = f" and {len(self.spans) - max_spans} more" if len(self.spans) > max_spans else ""
        return f"{head}: frames {shown}{more} (more than feet can give: a tracking policy has to deviate there)"

    def to_json(self) -> dict:
        """The fields as ``meta.json`` holds them (spans as lists)."""
        return {"outside": self.outside, "unsupported": self.unsupported, "spans": [list(s) for s in self.spans],
                "margin": self.margin, "min_support": self.min_support}


def followability(motion: Motion, margin: float = 0.10, min_support: float = 0.5, floor: float = 0.0,
                  touch: float = 0.03, bridge: int = 3, min_span: int = 3) -> Followability:
    """Where ``motion`` asks for a centre of pressure more than ``margin`` m outside the feet in
    contact, or for more than ``min_support`` body weights from the ground with nothing touching
    it (:class:`Followability`).

    Contacts are the motion's own; without them (an imported motion on a flat floor at height
    ``floor``), a foot touches the floor when its sole comes within ``touch`` m of it, sliding or
    not: a sliding foot still pushes, a hovering one cannot. Flagged frames closer than
    ``bridge`` frames are one span; spans shorter than ``min_span`` frames are left out of
    ``spans`` (not of the shares).
    """
    if motion.contacts is None:
        motion = replace(motion, contacts=_feet_on_floor(motion, floor, touch))
    balance = motion_balance(motion)
    judged = np.isfinite(balance.outside)
    unbalanced = np.where(judged, balance.outside, -np.inf) > margin
    unsupported = ~motion.contacts.any(axis=1) & (balance.vertical_force > min_support)
    return Followability(outside=float(unbalanced[judged].mean()) if judged.any() else 0.0,
                         unsupported=float(unsupported.mean()), spans=_spans(unbalanced | unsupported, bridge, min_span),
                         margin=margin, min_support=min_support)


def plant_supporting_feet(motion: Motion, model: mujoco.MjModel | None = None, min_support: float = 0.5,
                          near: float = 0.10, reach: float = 0.10, blend: float = 0.1, floor: float = 0.0) -> Motion:
    """``motion`` with the feet it stands on put on the floor (at height ``floor``): in every frame
    where the ground must carry more than ``min_support`` body weights, the foot nearest the centre
    of pressure the motion needs is lowered onto the floor if it hovers less than ``reach`` m above
    it, by bending its leg (:func:`crisp_gym.motion.lower_feet`, fading over ``blend`` seconds).
    A sole carries a centre of pressure up to ``near`` m outside it (the margin :func:`followability`
    allows); one farther from either sole but within ``near`` of their joint support polygon needs
    both feet. A foot in the air that carries nothing keeps its height, and so does the pelvis.

    A capture retargeted onto another body's legs lands late or hovers where the person stood:
    CMU 131_01's side lunge (frames 86-91) asks the ground for 1.0-1.5 body weights under the right
    foot while that sole is still 4-6 cm up, so a simulated body cannot stop its sideways fall
    where the reference does. As :func:`crisp_gym.motion.plant_feet` does, a foot within
    ``PLANT_TOLERANCE`` (2 mm) of the floor counts as on it, and a lowered one stops there.
    """
    model = build_humanoid(HumanoidConfig()) if model is None else model
    data = mujoco.MjData(model)
    motion = motion.in_humanoid_order()
    balance = motion_balance(replace(motion, contacts=None))  # every foot counted as touching
    sole = side_sole_heights(motion, model)
    soles = _sole_boxes(model)
    sides = [[BODY_NAMES.index(b) for b in FEET[:2]], [BODY_NAMES.index(b) for b in FEET[2:]]]
    qpos = motion.qpos()
    stands = np.zeros((motion.num_frames, 2), dtype=bool)
    for k in np.flatnonzero((balance.vertical_force > min_support) & np.isfinite(balance.cop).all(axis=1)):
        data.qpos[:] = qpos[k]
        mujoco.mj_kinematics(model, data)
        corners = [np.concatenate([_sole_corners(model, data, soles[i]) for i in side])[:, :2] for side in sides]
        outside = [distance_outside_hull(c, balance.cop[k]) for c in corners]
        nearest = int(np.argmin(outside))
        between = outside[nearest] >= near and distance_outside_hull(np.concatenate(corners), balance.cop[k]) < near
        for i in ((0, 1) if between else (nearest,)):
            stands[k, i] = floor + PLANT_TOLERANCE < sole[k, i] < floor + reach
    return lower_feet(motion, model, stands, floor + PLANT_TOLERANCE - sole, blend, floor, sole)


def _feet_on_floor(motion: Motion, floor: float, touch: float) -> np.ndarray:
    """(T, 24) bool: the foot bodies whose soles reach within ``touch`` of ``floor``."""
    model = build_humanoid(HumanoidConfig())
    data = mujoco.MjData(model)
    soles = _sole_boxes(model)
    qpos = motion.in_humanoid_order().qpos()
    out = np.zeros((len(qpos), len(BODY_NAMES)), dtype=bool)
    for k in range(len(qpos)):
        data.qpos[:] = qpos[k]
        mujoco.mj_kinematics(model, data)
        for i, geoms in soles.items():
            out[k, i] = _sole_corners(model, data, geoms)[:, 2].min() <= floor + touch
    return out


def _sole_boxes(model: mujoco.MjModel) -> dict[int, list[int]]:
    """Each foot body's index in ``BODY_NAMES`` with its box geoms (the soles)."""
    return {BODY_NAMES.index(b): [g for g in range(model.ngeom) if model.geom_bodyid[g] == model.body(b).id
                                  and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX] for b in FEET}


def _sole_corners(model: mujoco.MjModel, data: mujoco.MjData, geoms: list[int]) -> np.ndarray:
    """(4 len(geoms), 3) world corners of the bottom faces (local -z) of the box ``geoms``."""
    bottom = np.array([[x, y, -1.0] for x in (-1.0, 1.0) for y in (-1.0, 1.0)])
    return np.concatenate([data.geom_xpos[g] + (data.geom_xmat[g].reshape(3, 3) @ (bottom * model.geom_size[g]).T).T
                           for g in geoms])


def _spans(flags: np.ndarray, bridge: int, min_span: int) -> tuple[tuple[int, int], ...]:
    """Runs of ``flags`` as ``(first, end)``, runs less than ``bridge`` frames apart joined,
    runs shorter than ``min_span`` dropped."""
    runs: list[list[int]] = []
    for k in np.flatnonzero(flags):
        if runs and k - runs[-1][1] < bridge:
            runs[-1][1] = int(k) + 1
        else:
            runs.append([int(k), int(k) + 1])
    return tuple((a, b) for a, b in runs if b - a >= min_span)
