"""Physical-plausibility metrics of a motion in a scene of boxes, shared by all parts of the project.

A reconstructed (or generated) clip is only useful for simulation if the humanoid's feet do not
slide while they bear weight, its body does not sink into the scene, and the bodies said to be
in contact actually touch a support. These functions measure exactly that; all lengths are in
metres, speeds in metres per second, and arrays are per frame (T) and per body (B).

The array functions are pure; :func:`scene_penetration`, :func:`sole_points` and
:func:`motion_plausibility` pose the humanoid kinematically in a MuJoCo model to produce the
arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from crisp_gym.humanoid import BODY_NAMES, FEET, HumanoidConfig, build_humanoid_spec
from crisp_gym.motion import Motion, humanoid_qpos_adr
from crisp_gym.scene import Box, add_boxes

SKATING_THRESHOLD = 0.075
"""m/s: a contacting foot faster than this is sliding (2.5 mm per frame at 30 fps, the usual
per-frame threshold of foot-skating metrics in the motion-synthesis literature)."""


@dataclass(frozen=True)
class SkatingStats:
    """Foot skating over the frames where a foot is in contact.

    Attributes:
        mean_speed: mean horizontal speed of contacting feet (m/s); 0 when nothing is in contact.
        max_speed: the largest such speed (m/s).
        fraction_over: share of contact samples faster than the threshold (0-1).
        samples: number of (frame pair, body) samples in contact at both frames.
    """

    mean_speed: float
    max_speed: float
    fraction_over: float
    samples: int


def foot_skating(positions: np.ndarray, contacts: np.ndarray, fps: float,
                 threshold: float = SKATING_THRESHOLD) -> SkatingStats:
    """Horizontal sliding of bodies while in contact.

    Args:
        positions: (T, B) x 3 world positions of the foot bodies (m).
        contacts: (T, B) bool, whether each body is in contact.
        fps: frames per second.
        threshold: speed above which a sample counts as skating (m/s).

    A sample is the displacement between consecutive frames of a body in contact at both, so
    a foot that lands or lifts off is not counted as sliding.
    """
    positions = np.asarray(positions, dtype=float)
    contacts = np.asarray(contacts, dtype=bool)
    if positions.ndim != 3 or positions.shape[2] != 3 or contacts.shape != positions.shape[:2]:
        raise ValueError(f"positions must be (T, B, 3) and contacts (T, B), got {positions.shape} "
                         f"and {contacts.shape}")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    speed = np.linalg.norm(np.diff(positions[..., :2], axis=0), axis=2) * fps
    both = contacts[1:] & contacts[:-1]
    sliding = speed[both]
    if sliding.size == 0:
        return SkatingStats(0.0, 0.0, 0.0, 0)
    return SkatingStats(mean_speed=float(sliding.mean()), max_speed=float(sliding.max()),
                        fraction_over=float(np.mean(sliding > threshold)), samples=int(sliding.size))


def box_signed_distance(points: np.ndarray, boxes: list[Box]) -> np.ndarray:
    """(N,) signed distance of ``points`` (N, 3) to the union of ``boxes``: negative inside
    (minus the depth to the nearest face), positive outside (exact Euclidean distance)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if not boxes:
        raise ValueError("need at least one box")
    best = np.full(len(points), np.inf)
    for box in boxes:
        q = np.abs((points - box.center) @ box.rotation) - box.half_size
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        best = np.minimum(best, outside + inside)
    return best


def support_tops(xy: np.ndarray, boxes: list[Box]) -> np.ndarray:
    """(N, K) height of each box's upper surface above the points ``xy`` (N, 2); NaN where a
    vertical line through the point misses the box. Works for rotated boxes (slab test)."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    tops = np.full((len(xy), len(boxes)), np.nan)
    for k, box in enumerate(boxes):
        # Line p(z) = (x, y, z); in box coordinates local = R^T (p - c) = a + z * d.
        a = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1) - box.center
        a = a @ box.rotation
        d = box.rotation[2]  # R^T e_z
        lo = np.full(len(xy), -np.inf)
        hi = np.full(len(xy), np.inf)
        hit = np.ones(len(xy), dtype=bool)
        for axis in range(3):
            if abs(d[axis]) < 1e-12:
                hit &= np.abs(a[:, axis]) <= box.half_size[axis]
                continue
            z1 = (-box.half_size[axis] - a[:, axis]) / d[axis]
            z2 = (box.half_size[axis] - a[:, axis]) / d[axis]
            lo = np.maximum(lo, np.minimum(z1, z2))
            hi = np.minimum(hi, np.maximum(z1, z2))
        hit &= lo <= hi
        tops[hit, k] = hi[hit]
    return tops


def contact_height_error(soles: np.ndarray, contacts: np.ndarray, boxes: list[Box]) -> np.ndarray:
    """Distance from each contacting body's sole point to the nearest support top below or above it.

    Args:
        soles: (T, B, 3) sole points (e.g. :func:`sole_points`).
        contacts: (T, B) bool.
        boxes: the scene.

    Returns:
        (K,) absolute vertical errors (m) of the K contacting samples, in frame-major order;
        ``inf`` where no box lies under the sole at all.
    """
    soles = np.asarray(soles, dtype=float)
    contacts = np.asarray(contacts, dtype=bool)
    if soles.ndim != 3 or contacts.shape != soles.shape[:2]:
        raise ValueError(f"soles must be (T, B, 3) and contacts (T, B), got {soles.shape}, {contacts.shape}")
    points = soles[contacts]
    if len(points) == 0:
        return np.zeros(0)
    gaps = np.abs(support_tops(points[:, :2], boxes) - points[:, 2:3])
    return np.where(np.all(np.isnan(gaps), axis=1), np.inf, np.nanmin(np.where(np.isnan(gaps), np.inf, gaps), axis=1))


def scene_model(boxes: list[Box], height: float | None = None) -> mujoco.MjModel:
    """The humanoid composed with ``boxes`` (collision bits: only humanoid-scene pairs collide)."""
    spec = build_humanoid_spec(HumanoidConfig(height=height) if height else None)
    add_boxes(spec, boxes)
    return spec.compile()


def scene_penetration(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """(T,) deepest penetration (m, >= 0) of the posed humanoid into the scene in each frame.

    ``qpos`` is (T, 76) humanoid qpos (e.g. :meth:`Motion.qpos`); the model is the humanoid
    plus the scene (:func:`scene_model`), whose collision bits make ``mj_collision`` report
    exactly the humanoid-scene contacts, with ``dist < 0`` when they overlap.
    """
    qpos = np.atleast_2d(np.asarray(qpos, dtype=float))
    data = mujoco.MjData(model)
    adr = humanoid_qpos_adr(model)
    depth = np.zeros(len(qpos))
    for k, q in enumerate(qpos):
        data.qpos[adr:adr + q.shape[0]] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
        if data.ncon:
            depth[k] = max(0.0, -float(data.contact.dist[:data.ncon].min()))
    return depth


def sole_points(model: mujoco.MjModel, qpos: np.ndarray, bodies: tuple[str, ...] = FEET) -> np.ndarray:
    """(T, B, 3) centre of the lowest face of each body's first box geom (the sole of a foot)."""
    qpos = np.atleast_2d(np.asarray(qpos, dtype=float))
    data = mujoco.MjData(model)
    adr = humanoid_qpos_adr(model)
    geoms = []
    for name in bodies:
        body = model.body(name).id
        found = [g for g in range(model.ngeom)
                 if model.geom_bodyid[g] == body and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX]
        if not found:
            raise ValueError(f"body {name!r} has no box geom to take a sole from")
        geoms.append(found[0])
    out = np.empty((len(qpos), len(bodies), 3))
    for k, q in enumerate(qpos):
        data.qpos[adr:adr + q.shape[0]] = q
        mujoco.mj_kinematics(model, data)
        for i, g in enumerate(geoms):
            rot = data.geom_xmat[g].reshape(3, 3)
            axis = int(np.argmax(np.abs(rot[2])))  # the box axis closest to vertical
            sign = -np.sign(rot[2, axis])
            out[k, i] = data.geom_xpos[g] + sign * model.geom_size[g][axis] * rot[:, axis]
    return out


def foot_heights(soles: np.ndarray) -> np.ndarray:
    """(T, 2) height of each foot (left, right): the lower of its ankle's and toe's sole points,
    from :func:`sole_points` with the default :data:`~crisp_gym.humanoid.FEET`."""
    return np.minimum(soles[:, 0::2, 2], soles[:, 1::2, 2])


@dataclass(frozen=True)
class Plausibility:
    """Summary of :func:`motion_plausibility`.

    Attributes:
        skating: foot skating of the contacting foot bodies (their sole points).
        penetration_max, penetration_mean: deepest penetration over the clip, and its mean over
            frames (m).
        contact_height_max, contact_height_mean: sole-to-support error of contacting foot
            bodies (m); ``inf`` if a contacting foot has no support under it.
        contact_samples: number of (frame, foot body) contact samples.
    """

    skating: SkatingStats
    penetration_max: float
    penetration_mean: float
    contact_height_max: float
    contact_height_mean: float
    contact_samples: int


def motion_plausibility(boxes: list[Box], motion: Motion, model: mujoco.MjModel | None = None) -> Plausibility:
    """Skating, penetration and contact-height error of ``motion`` (with ``contacts``) in ``boxes``."""
    if motion.contacts is None:
        raise ValueError("the motion has no contacts; plausibility needs the contact labels")
    motion = motion.in_humanoid_order()
    model = model or scene_model(boxes)
    qpos = motion.qpos()
    feet = [BODY_NAMES.index(b) for b in FEET]
    contacts = motion.contacts[:, feet]
    soles = sole_points(model, qpos)
    skating = foot_skating(soles, contacts, motion.fps)
    depth = scene_penetration(model, qpos)
    errors = contact_height_error(soles, contacts, boxes)
    return Plausibility(
        skating=skating, penetration_max=float(depth.max()), penetration_mean=float(depth.mean()),
        contact_height_max=float(errors.max()) if errors.size else 0.0,
        contact_height_mean=float(errors.mean()) if errors.size else 0.0, contact_samples=int(errors.size))
