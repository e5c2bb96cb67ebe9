"""Human-scene contacts: where they come from, which ones to trust, and the support they imply.

The paper (Sec. 3.3, appendix "Contact-guided scene completion", Algorithm 1 step 4) completes
the scene where the camera never saw the surface a person sat or stood on. Three stages:

1. **Contact sources** give a per-frame confidence for each of the humanoid's 24 bodies
   (:class:`ContactEvidence`):

   * :func:`kinematic_contacts`, from the motion alone (no learned model). Each body part has a
     physical cue: a foot is in contact when its sole is at its lowest height near that spot
     (a foot held above a step is not); the pelvis and thighs when the pelvis is at sitting
     height above the feet *and* the body could not balance on its feet alone (its centre of
     mass lies behind them) while the seat's patch closes the support polygon (a squat or a
     pelvis passing over a seat is not sitting); a hand when it is the missing support of an
     unbalanced, unseated body; the back when a seated trunk reclines beyond what a person
     holds without a backrest.
   * :func:`load_external_contacts`: InteractVLM-style per-vertex probabilities
     (``pred_contact_3d_smplh``, (T, 6890)) with a vertex→body map, or explicit world-frame
     points (``contacts.npz``: ``frame``, ``body``, ``point``, ``prob``).

2. **Temporal–kinematic filtering** (:func:`filter_contacts`), the paper's non-maximum
   suppression: a body's contact is kept only where its confidence stays >= τ for L
   consecutive frames while the body's contact patch moves slower than ν, and each such window
   yields its most stationary frame. Windows of a body that lie above a lower window of the same
   body at the same spot a moment before or after are suppressed too: that is an "imminent
   contact" (a foot hovering over a step before it lands), which the paper reports learned
   detectors over-predict and which stillness alone cannot reject.

3. **Support completion** (:func:`complete_support`): the filtered contact patches not already
   resting on the scene are clustered per surface, a plane is fitted with RANSAC, and a box
   (``source="contact"``) is made whose top is that plane and whose footprint covers the patches
   with a margin; it is extended to a perpendicular primitive it nearly touches (a seat to its
   chair back, a platform top to its riser).

A body's *contact patch* is a few world points on the part of the humanoid that touches a
support (:func:`body_geometry`): the four corners and centre of the lowest face of a foot or
hand box; the underside of the proximal half of a thigh; the back side of a trunk segment; the
underside of any other capsule. The humanoid has no buttocks (its pelvis capsule rides about
10 cm above where a person's buttocks meet a seat), so the pelvis patch is its capsule axis
dropped to the level of the thighs' undersides at the hips.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation
from sklearn.cluster import DBSCAN

from crisp_gym.atomic import atomic_path
from crisp_gym.balance import distance_outside_hull
from crisp_gym.geometry import min_area_rectangle, plane_frame, ransac_height_plane, snap_to_gravity
from crisp_gym.humanoid import BODY_NAMES, build_humanoid
from crisp_gym.metrics import box_signed_distance
from crisp_gym.motion import Motion, compute_kinematics
from crisp_gym.npz import read_npy, read_npz
from crisp_gym.scene import Box
from crisp_gym.smpl import SMPL_JOINT_NAMES, SMPL_TO_BODY

PARTS: dict[str, tuple[str, ...]] = {
    "foot": ("L_Ankle", "L_Toe", "R_Ankle", "R_Toe"),
    "seat": ("Pelvis", "L_Hip", "R_Hip"),
    "hand": ("L_Hand", "R_Hand"),
    "back": ("Torso", "Spine", "Chest"),
}
"""Body-part groups with their own contact cue and filter thresholds; other bodies are ``"other"``."""

PART_OF: dict[str, str] = {body: next((p for p, bodies in PARTS.items() if body in bodies), "other")
                           for body in BODY_NAMES}
"""Body name -> its part group."""

NUM_SMPL_VERTICES = 6890
"""Vertices of the SMPL(-H) mesh that InteractVLM's ``pred_contact_3d_smplh`` scores."""

_UP = np.array([0.0, 0.0, 1.0])
_SEAT_THIGH_SPAN = 0.5  # fraction of the thigh from the hip that bears the seated weight


# --------------------------------------------------------------------------- body geometry


@dataclass(frozen=True)
class BodyGeometry:
    """Where each body of a posed motion would touch a support, frame by frame (world frame).

    Attributes:
        fps: frame rate of the motion.
        patches: 24 arrays (one per body, :data:`BODY_NAMES` order) of shape (T, K, 3): the
            body's contact patch in every frame (see the module docstring).
        speed: (T, 24) speed of each patch's centroid (m/s), by central differences.
        body_pos: (T, 24, 3) body (joint) positions.
        forward: (T, 3) the pelvis's horizontal facing direction (unit).
        com: (T, 3) whole-body centre of mass.
        standing_pelvis: height of the pelvis above the soles in the humanoid's rest pose (m).
    """

    fps: float
    patches: tuple[np.ndarray, ...]
    speed: np.ndarray
    body_pos: np.ndarray
    forward: np.ndarray
    com: np.ndarray
    standing_pelvis: float

    @property
    def num_frames(self) -> int:
        return self.speed.shape[0]

    def centroid(self, body: int) -> np.ndarray:
        """(T, 3) centroid of one body's patch."""
        return self.patches[body].mean(axis=1)


def _body_geom(model: mujoco.MjModel, body: str) -> int:
    """The (first) collision geom of a humanoid body."""
    bid = model.body(body).id
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == bid]
    if not geoms:
        raise ValueError(f"humanoid body {body!r} has no geom to take a contact patch from")
    return geoms[0]


def _geom_poses(model: mujoco.MjModel, geom: int, pos: np.ndarray, rot: Rotation) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) world centre and (T, 3, 3) world axes of a geom from its body's poses."""
    local = Rotation.from_quat(model.geom_quat[geom], scalar_first=True)
    return pos + rot.apply(model.geom_pos[geom]), (rot * local).as_matrix()


def _box_sole(center: np.ndarray, axes: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(T, 5, 3) centre and corners of the lowest face of a box in every frame."""
    t = np.arange(len(center))
    vertical = np.argmax(np.abs(axes[:, 2, :]), axis=1)  # the box axis closest to z
    sign = -np.sign(axes[t, 2, vertical])
    face = center + (sign * half[vertical])[:, None] * axes[t, :, vertical]
    others = np.array([[a for a in range(3) if a != v] for v in range(3)])[vertical]
    u = axes[t, :, others[:, 0]] * half[others[:, 0]][:, None]
    v = axes[t, :, others[:, 1]] * half[others[:, 1]][:, None]
    corners = [face + su * u + sv * v for su in (-1, 1) for sv in (-1, 1)]
    return np.stack([face, *corners], axis=1)


def _capsule_line(center: np.ndarray, axes: np.ndarray, size: np.ndarray, joint: np.ndarray,
                  span: float, side: np.ndarray) -> np.ndarray:
    """(T, 3, 3) points on a capsule's surface facing ``side`` (T, 3), along its axis from the
    end at ``joint`` over the fraction ``span`` of its length."""
    radius, half_length = size[0], size[1]
    axis = axes[:, :, 2]
    # Orient the axis from the joint end to the free end.
    flip = np.einsum("ti,ti->t", joint - center, axis) > 0
    axis = np.where(flip[:, None], -axis, axis)
    start = center - half_length * axis
    offset = side - np.einsum("ti,ti->t", side, axis)[:, None] * axis
    norm = np.linalg.norm(offset, axis=1, keepdims=True)
    # Along the side direction itself the surface point is undefined; fall back to ``side``.
    offset = np.where(norm > 1e-6, offset / np.maximum(norm, 1e-12), side)
    fractions = np.array([0.0, 0.5, 1.0]) * span
    return np.stack([start + f * 2 * half_length * axis + radius * offset for f in fractions], axis=1)


def _standing_pelvis_height(model: mujoco.MjModel) -> float:
    """Pelvis origin above the lowest foot-box point in the rest pose."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    soles = [data.geom_xpos[g][2] - model.geom_size[g][2]
             for g in (_body_geom(model, b) for b in PARTS["foot"])]
    return float(data.xpos[model.body("Pelvis").id][2] - min(soles))


def body_geometry(motion: Motion, model: mujoco.MjModel | None = None) -> BodyGeometry:
    """Contact patches, their speeds and the centre of mass of ``motion`` posed on ``model``.

    ``model`` is the humanoid the motion was made for (default: :func:`build_humanoid`).
    """
    model = model or build_humanoid()
    motion = motion.in_humanoid_order()
    kin = compute_kinematics(motion, model)
    t = motion.num_frames
    rots = [Rotation.from_quat(kin.body_quat[:, i], scalar_first=True) for i in range(len(BODY_NAMES))]
    forward = rots[0].apply([1.0, 0.0, 0.0]) * [1.0, 1.0, 0.0]
    forward /= np.maximum(np.linalg.norm(forward, axis=1, keepdims=True), 1e-9)
    down = np.broadcast_to(-_UP, (t, 3))

    patches: list[np.ndarray | None] = [None] * len(BODY_NAMES)
    for i, body in enumerate(BODY_NAMES):
        g = _body_geom(model, body)
        center, axes = _geom_poses(model, g, kin.body_pos[:, i], rots[i])
        size = model.geom_size[g]
        kind = model.geom_type[g]
        if kind == mujoco.mjtGeom.mjGEOM_BOX:
            patches[i] = _box_sole(center, axes, size)
        elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            patches[i] = (center - size[0] * _UP)[:, None, :]
        elif body == "Pelvis":
            continue  # needs the thighs; below
        elif PART_OF[body] == "back":
            patches[i] = _capsule_line(center, axes, size, kin.body_pos[:, i], 1.0, -forward)
        else:
            span = _SEAT_THIGH_SPAN if PART_OF[body] == "seat" else 1.0
            patches[i] = _capsule_line(center, axes, size, kin.body_pos[:, i], span, down)
    pelvis = BODY_NAMES.index("Pelvis")
    g = _body_geom(model, "Pelvis")
    center, axes = _geom_poses(model, g, kin.body_pos[:, pelvis], rots[pelvis])
    half = model.geom_size[g][1] * axes[:, :, 2]
    axis_points = np.stack([center - half, center, center + half], axis=1)
    hips = [patches[BODY_NAMES.index(b)][:, 0, 2] for b in ("L_Hip", "R_Hip")]
    axis_points[:, :, 2] = np.mean(hips, axis=0)[:, None]
    patches[pelvis] = axis_points

    dt = 1.0 / motion.fps
    speed = np.stack([np.linalg.norm(np.gradient(p.mean(axis=1), dt, axis=0), axis=1) for p in patches], axis=1)
    mass = model.body_mass[[model.body(b).id for b in BODY_NAMES]]
    ipos = np.stack([rots[i].apply(model.body_ipos[model.body(b).id]) for i, b in enumerate(BODY_NAMES)], axis=1)
    com = np.einsum("b,tbi->ti", mass, kin.body_pos + ipos) / mass.sum()
    return BodyGeometry(fps=motion.fps, patches=tuple(patches), speed=speed, body_pos=kin.body_pos,
                        forward=forward, com=com, standing_pelvis=_standing_pelvis_height(model))


# --------------------------------------------------------------------------- evidence


@dataclass(frozen=True)
class ContactEvidence:
    """Per-frame contact confidence of the humanoid's bodies, from one source.

    Attributes:
        prob: (T, 24) confidence in [0, 1] per frame and body (:data:`BODY_NAMES` order).
        source: where it came from: ``"kinematic"``, ``"vertices"`` (per-vertex probabilities)
            or ``"points"`` (explicit contact points) from this module's sources.
        point_frame: (M,) frame of each explicit world contact point (empty when the source
            gives none; the humanoid's own patches are used then).
        point_body: (M,) body index of each explicit point.
        points: (M, 3) explicit world contact points.
    """

    prob: np.ndarray
    source: str
    point_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    point_body: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self) -> None:
        prob = np.asarray(self.prob, dtype=float)
        if prob.ndim != 2 or prob.shape[1] != len(BODY_NAMES):
            raise ValueError(f"prob must have shape (T, {len(BODY_NAMES)}), got {prob.shape}")
        if not np.all(np.isfinite(prob)) or prob.min(initial=0.0) < 0 or prob.max(initial=0.0) > 1:
            raise ValueError("prob must hold finite confidences in [0, 1]")
        frames = np.asarray(self.point_frame, dtype=int).reshape(-1)
        bodies = np.asarray(self.point_body, dtype=int).reshape(-1)
        points = np.asarray(self.points, dtype=float).reshape(-1, 3)
        if not len(frames) == len(bodies) == len(points):
            raise ValueError(f"point_frame, point_body and points must have the same length, got "
                             f"{len(frames)}, {len(bodies)}, {len(points)}")
        object.__setattr__(self, "prob", prob)
        object.__setattr__(self, "point_frame", frames)
        object.__setattr__(self, "point_body", bodies)
        object.__setattr__(self, "points", points)

    @property
    def num_frames(self) -> int:
        return self.prob.shape[0]


@dataclass(frozen=True)
class KinematicConfig:
    """Cues of :func:`kinematic_contacts`. Confidences are linear ramps between the stated ends.

    Attributes:
        foot_lift: a foot patch within this height (m) of its lowest height near the same spot
            has confidence 1, falling to 0 at twice it; a sole held higher hovers.
        foot_window: half-width (s) of the time window searched for that lowest height.
        foot_radius: horizontal radius (m) of "the same spot" (about half a foot length).
        sit_height: pelvis height above the lowest foot, as a fraction of the humanoid's standing
            pelvis height, at or below which the pelvis is low enough to sit (a 0.40-0.48 m chair
            puts it near 0.63).
        sit_fade: the sitting confidence falls to 0 at ``sit_height + sit_fade``.
        balance_margin: m; the centre of mass this far outside the feet's support polygon
            cannot balance on the feet (confidence 1, from 0 at the polygon's edge), and a
            patch that brings it this far inside closes the support.
        hand_below_shoulder: m; a supporting hand is at least this far below its shoulder.
        back_recline_deg: a seated trunk reclined at least this far behind vertical leans on a
            backrest (confidence 1, from 0 at 5° less); people sit upright at 0-15°.
    """

    foot_lift: float = 0.02
    foot_window: float = 1.0
    foot_radius: float = 0.12
    sit_height: float = 0.8
    sit_fade: float = 0.1
    balance_margin: float = 0.05
    hand_below_shoulder: float = 0.1
    back_recline_deg: float = 20.0


def _ramp(x: np.ndarray | float, zero: float, one: float) -> np.ndarray:
    """Linear ramp: 0 at ``zero``, 1 at ``one`` (either order), clipped."""
    return np.clip((np.asarray(x, dtype=float) - zero) / (one - zero), 0.0, 1.0)


def _foot_confidence(geo: BodyGeometry, cfg: KinematicConfig) -> np.ndarray:
    """(T, 4) lowness of each foot body: its patch height over its lowest height nearby in space and time."""
    t = geo.num_frames
    w = max(1, int(round(cfg.foot_window * geo.fps)))
    out = np.empty((t, len(PARTS["foot"])))
    for j, body in enumerate(PARTS["foot"]):
        c = geo.centroid(BODY_NAMES.index(body))
        lowest = c[:, 2].copy()
        for shift in range(1, w + 1):
            for a, b in ((slice(shift, None), slice(None, -shift)), (slice(None, -shift), slice(shift, None))):
                near = np.linalg.norm(c[a, :2] - c[b, :2], axis=1) <= cfg.foot_radius
                lowest[a] = np.where(near, np.minimum(lowest[a], c[b, 2]), lowest[a])
        out[:, j] = _ramp(c[:, 2] - lowest, 2 * cfg.foot_lift, cfg.foot_lift)
    return out


def kinematic_contacts(motion: Motion, cfg: KinematicConfig | None = None,
                       geometry: BodyGeometry | None = None) -> ContactEvidence:
    """Contact confidence from the motion alone (see the module docstring for the cues).

    ``geometry`` is :func:`body_geometry` of ``motion`` (computed when not given). Stillness
    and persistence are left to :func:`filter_contacts`; these confidences say only whether
    the pose needs (or allows) a support there.
    """
    cfg = cfg or KinematicConfig()
    geo = geometry or body_geometry(motion)
    if geo.num_frames != motion.num_frames:
        raise ValueError(f"geometry has {geo.num_frames} frames but the motion {motion.num_frames}")
    idx = {b: BODY_NAMES.index(b) for b in BODY_NAMES}
    prob = np.zeros((geo.num_frames, len(BODY_NAMES)))
    feet = _foot_confidence(geo, cfg)
    for j, body in enumerate(PARTS["foot"]):
        prob[:, idx[body]] = feet[:, j]

    sole_z = np.min([geo.centroid(idx[b])[:, 2] for b in PARTS["foot"]], axis=0)
    low = _ramp((geo.body_pos[:, idx["Pelvis"], 2] - sole_z) / geo.standing_pelvis,
                cfg.sit_height + cfg.sit_fade, cfg.sit_height)
    seat_patch = np.concatenate([geo.patches[idx[b]] for b in PARTS["seat"]], axis=1)
    m = cfg.balance_margin
    recline = np.degrees(np.arctan2(
        -np.einsum("ti,ti->t", geo.body_pos[:, idx["Chest"]] - geo.body_pos[:, idx["Pelvis"]], geo.forward),
        geo.body_pos[:, idx["Chest"], 2] - geo.body_pos[:, idx["Pelvis"], 2]))
    for k in range(geo.num_frames):
        standing = [geo.patches[idx[b]][k, :, :2] for j, b in enumerate(PARTS["foot"]) if feet[k, j] >= 0.5]
        feet_xy = np.concatenate(standing) if standing else np.zeros((0, 2))
        com = geo.com[k, :2]
        unbalanced = float(_ramp(distance_outside_hull(feet_xy, com), 0.0, m))  # inf (no feet down) -> 1
        if unbalanced == 0.0:
            continue
        closes = _ramp(distance_outside_hull(np.concatenate([feet_xy, seat_patch[k, :, :2]]), com), m, 0.0)
        seat = float(low[k] * unbalanced * closes)
        for body in PARTS["seat"]:
            prob[k, idx[body]] = seat
        for body in PARTS["back"]:
            prob[k, idx[body]] = seat * _ramp(recline[k], cfg.back_recline_deg - 5.0, cfg.back_recline_deg)
        for hand, shoulder in (("L_Hand", "L_Shoulder"), ("R_Hand", "R_Shoulder")):
            patch = geo.patches[idx[hand]][k]
            below = _ramp(geo.body_pos[k, idx[shoulder], 2] - patch[:, 2].mean(), 0.0, cfg.hand_below_shoulder)
            closes = _ramp(distance_outside_hull(np.concatenate([feet_xy, patch[:, :2]]), com), m, 0.0)
            prob[k, idx[hand]] = float(unbalanced * closes * below * (1.0 - seat))
    return ContactEvidence(prob=prob, source="kinematic")


def _body_index(name: str | bytes) -> int:
    """Index in :data:`BODY_NAMES` of one of our body names or an SMPL joint name."""
    name = name.decode() if isinstance(name, bytes) else str(name)
    if name in BODY_NAMES:
        return BODY_NAMES.index(name)
    if name in SMPL_TO_BODY:
        return BODY_NAMES.index(SMPL_TO_BODY[name])
    raise ValueError(f"unknown body {name!r}; expected one of {BODY_NAMES} or an SMPL joint name "
                     f"{SMPL_JOINT_NAMES}")


def _vertex_bodies(vertex_body: np.ndarray) -> np.ndarray:
    """(6890,) body index per SMPL vertex (-1 unmapped) from names or SMPL joint indices."""
    vertex_body = np.asarray(vertex_body).reshape(-1)
    if vertex_body.shape != (NUM_SMPL_VERTICES,):
        raise ValueError(f"vertex_body must have {NUM_SMPL_VERTICES} entries (one per SMPL vertex), "
                         f"got {vertex_body.shape}")
    if vertex_body.dtype.kind in "iu":
        if vertex_body.max() >= len(SMPL_JOINT_NAMES):
            raise ValueError(f"integer vertex_body entries are SMPL joint indices 0-23 (or -1 for "
                             f"unmapped), got {vertex_body.max()}")
        names = np.array(SMPL_JOINT_NAMES + ("",))[np.where(vertex_body < 0, -1, vertex_body)]
    else:
        names = vertex_body.astype(str)
    return np.array([-1 if n == "" else _body_index(n) for n in names])


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    if path.suffix.lower() == ".npy":  # a bare .npy holds InteractVLM's per-vertex array
        return {"pred_contact_3d_smplh": read_npy(path, "contact file")}
    return read_npz(path, "contact file (.npz or InteractVLM .npy)")


def load_external_contacts(path: str | Path, motion: Motion, vertex_map: str | Path | None = None,
                           vertex_quantile: float = 0.9) -> ContactEvidence:
    """Contact evidence from a file produced outside the project.

    Two layouts are read:

    * explicit points, ``contacts.npz``: ``frame`` (M,) int, ``body`` (M,) body names (ours,
      e.g. ``"L_Ankle"``, or SMPL joint names), ``point`` (M, 3) world position (the frame of
      ``motion``), ``prob`` (M,) in [0, 1]. A body's confidence in a frame is its highest
      ``prob`` there; the filter uses the points themselves as the contact patch.
    * per-vertex probabilities, InteractVLM's ``pred_contact_3d_smplh`` (T, 6890) (an .npz key,
      or a bare .npy). Each vertex needs a body: ``vertex_body`` (6890,) in the same file or in
      ``vertex_map`` (an .npz), either body names or SMPL joint indices 0-23 (-1 or ``""`` for
      none) — ``weights.argmax(axis=1)`` of the SMPL model's skinning weights is such a map.
      A body's confidence is the ``vertex_quantile`` quantile of its vertices' probabilities
      (0.9: a tenth of the body must be confident; a lone vertex is not a contact); its patch is
      the humanoid's own (the SMPL mesh itself is not needed).

    The file's frames must be the motion's frames.
    """
    path = Path(path)
    data = _read_npz(path)
    t = motion.num_frames
    if {"frame", "body", "point", "prob"} <= set(data):
        frames = np.asarray(data["frame"]).reshape(-1)
        if frames.dtype.kind not in "iu":
            raise ValueError(f"{path}: 'frame' must hold integer frame indices, got {frames.dtype}")
        bodies = np.array([_body_index(b) for b in np.asarray(data["body"]).reshape(-1)], dtype=int)
        points = np.asarray(data["point"], dtype=float)
        probs = np.asarray(data["prob"], dtype=float).reshape(-1)
        if points.shape != (len(frames), 3) or len(bodies) != len(frames) or len(probs) != len(frames):
            raise ValueError(f"{path}: expected frame (M,), body (M,), point (M, 3), prob (M,), got "
                             f"{frames.shape}, {bodies.shape}, {points.shape}, {probs.shape}")
        if len(frames) and (frames.min() < 0 or frames.max() >= t):
            raise ValueError(f"{path}: frames must lie in [0, {t}) (the motion's frames), got "
                             f"{frames.min()}..{frames.max()}")
        if not (np.all(np.isfinite(points)) and np.all((probs >= 0) & (probs <= 1))):
            raise ValueError(f"{path}: points must be finite and prob within [0, 1]")
        prob = np.zeros((t, len(BODY_NAMES)))
        np.maximum.at(prob, (frames, bodies), probs)
        keep = probs > 0
        return ContactEvidence(prob=prob, source="points", point_frame=frames[keep], point_body=bodies[keep],
                               points=points[keep])
    if "pred_contact_3d_smplh" in data:
        scores = np.asarray(data["pred_contact_3d_smplh"], dtype=float)
        if scores.ndim != 2 or scores.shape != (t, NUM_SMPL_VERTICES):
            raise ValueError(f"{path}: pred_contact_3d_smplh must be (T={t}, {NUM_SMPL_VERTICES}) for this "
                             f"motion, got {scores.shape}")
        if "vertex_body" in data:
            vertex_body = data["vertex_body"]
        elif vertex_map is not None:
            mapping = _read_npz(Path(vertex_map))
            if "vertex_body" not in mapping:
                raise ValueError(f"{vertex_map} has no 'vertex_body' array (has {sorted(mapping)})")
            vertex_body = mapping["vertex_body"]
        else:
            raise ValueError(f"{path} holds per-vertex contacts; pass vertex_map (an .npz with "
                             f"'vertex_body' (6890,)) to say which body each vertex belongs to")
        if not 0.0 <= vertex_quantile <= 1.0:
            raise ValueError(f"vertex_quantile must be in [0, 1], got {vertex_quantile}")
        owner = _vertex_bodies(vertex_body)
        prob = np.zeros((t, len(BODY_NAMES)))
        for b in np.unique(owner[owner >= 0]):
            prob[:, b] = np.quantile(np.clip(scores[:, owner == b], 0.0, 1.0), vertex_quantile, axis=1)
        return ContactEvidence(prob=prob, source="vertices")
    raise ValueError(f"{path} is neither a contacts.npz (frame, body, point, prob) nor per-vertex "
                     f"contacts (pred_contact_3d_smplh); it has {sorted(data)}")


# --------------------------------------------------------------------------- filtering


@dataclass(frozen=True)
class PartFilter:
    """Thresholds of the temporal–kinematic filter for one body part.

    Attributes:
        threshold: τ, the confidence a contact must keep.
        min_duration: seconds it must be kept; L = ceil(min_duration * fps) frames.
        max_speed: ν, m/s the contact patch must stay below.
    """

    threshold: float
    min_duration: float
    max_speed: float


@dataclass(frozen=True)
class FilterConfig:
    """:func:`filter_contacts` settings.

    The paper gives no values for τ, L, ν. These are set from human motion, in seconds and
    m/s so they hold at any frame rate: a walking stance lasts 0.3-0.4 s and a sit seconds; a
    planted foot or a seated body moves well under 0.1 m/s, a passing one at about 1 m/s; a
    foot settling onto a step still creeps at up to ~0.2 m/s, a seat or a hand much less.

    A window is an imminent (or lingering) contact, and dropped, when a window of the same body
    lies lower by more than ``suppress_height``, within ``suppress_radius`` horizontally and
    ``suppress_horizon`` in time (start to end, either way): a surface cannot be under the
    higher patch where the same body rests lower a moment later. This applies to the parts
    that rest on a surface below them (all but the back).

    Attributes:
        foot, seat, hand, back, other: per-part thresholds (:data:`PARTS`).
        suppress_radius: m; about a foot length, so the two footprints overlap.
        suppress_height: m; above the height noise of a resting patch.
        suppress_horizon: s; a few steps' time.
    """

    foot: PartFilter = PartFilter(threshold=0.5, min_duration=0.15, max_speed=0.2)
    seat: PartFilter = PartFilter(threshold=0.5, min_duration=0.5, max_speed=0.15)
    hand: PartFilter = PartFilter(threshold=0.5, min_duration=0.3, max_speed=0.15)
    back: PartFilter = PartFilter(threshold=0.5, min_duration=0.5, max_speed=0.15)
    other: PartFilter = PartFilter(threshold=0.5, min_duration=0.3, max_speed=0.15)
    suppress_radius: float = 0.3
    suppress_height: float = 0.03
    suppress_horizon: float = 2.0

    def part(self, name: str) -> PartFilter:
        """The thresholds of part ``name`` (a key of :data:`PARTS`, or ``"other"``)."""
        return getattr(self, name)


@dataclass(frozen=True)
class Contact:
    """One filtered contact: a body resting on a surface for a window of frames.

    Attributes:
        body: body name; part: its group (:data:`PART_OF`).
        frame: the window's most stationary frame, where ``points`` were taken.
        start, stop: the window, frames ``[start, stop)``.
        prob: mean confidence over the window.
        points: (K, 3) world contact patch at ``frame``.
        normal: (3,) unit direction from the surface towards the body (up for a support below,
            the trunk's forward direction for a backrest).
    """

    body: str
    part: str
    frame: int
    start: int
    stop: int
    prob: float
    points: np.ndarray
    normal: np.ndarray


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs ``[start, stop)`` of True."""
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def _suppress_imminent(contacts: list[Contact], cfg: FilterConfig, fps: float) -> list[Contact]:
    """Drop windows lying above a lower window of the same body at the same spot, close in time."""
    horizon = cfg.suppress_horizon * fps
    keep = []
    centres = [c.points.mean(axis=0) for c in contacts]
    for c, centre in zip(contacts, centres):
        dominated = c.part != "back" and any(
            o.body == c.body and max(o.start - c.stop, c.start - o.stop) <= horizon
            and np.linalg.norm(other[:2] - centre[:2]) <= cfg.suppress_radius
            and other[2] < centre[2] - cfg.suppress_height
            for o, other in zip(contacts, centres))
        if not dominated:
            keep.append(c)
    return keep


def filter_contacts(evidence: ContactEvidence, motion: Motion, cfg: FilterConfig | None = None,
                    geometry: BodyGeometry | None = None) -> list[Contact]:
    """The paper's temporal–kinematic non-maximum suppression (see the module docstring).

    Per body: runs of frames with confidence >= τ and patch speed < ν, at least L frames long;
    each run gives one :class:`Contact` at its slowest frame, with the evidence's explicit points
    of that frame and body as the patch when it has some, else the humanoid's own patch. Runs
    above a lower run of the same body nearby in space and time are then dropped.
    """
    cfg = cfg or FilterConfig()
    geo = geometry or body_geometry(motion)
    if evidence.num_frames != motion.num_frames or geo.num_frames != motion.num_frames:
        raise ValueError(f"evidence ({evidence.num_frames} frames) and geometry ({geo.num_frames}) must "
                         f"cover the motion's {motion.num_frames} frames")
    contacts = []
    for b, body in enumerate(BODY_NAMES):
        part = PART_OF[body]
        pf = cfg.part(part)
        length = max(1, math.ceil(pf.min_duration * motion.fps - 1e-9))
        ok = (evidence.prob[:, b] >= pf.threshold) & (geo.speed[:, b] < pf.max_speed)
        for start, stop in _runs(ok):
            if stop - start < length:
                continue
            frame = start + int(np.argmin(geo.speed[start:stop, b]))
            explicit = (evidence.point_body == b) & (evidence.point_frame == frame)
            points = evidence.points[explicit] if explicit.any() else geo.patches[b][frame]
            normal = geo.forward[frame] if part == "back" else _UP
            contacts.append(Contact(body=body, part=part, frame=frame, start=start, stop=stop,
                                    prob=float(evidence.prob[start:stop, b].mean()),
                                    points=np.array(points, dtype=float), normal=np.array(normal, dtype=float)))
    return _suppress_imminent(contacts, cfg, motion.fps)


def contact_labels(contacts: list[Contact], num_frames: int) -> np.ndarray:
    """(T, 24) bool: the frames each body's filtered windows cover (comparable to ``motion.contacts``)."""
    labels = np.zeros((num_frames, len(BODY_NAMES)), dtype=bool)
    for c in contacts:
        labels[c.start:c.stop, BODY_NAMES.index(c.body)] = True
    return labels


def save_contacts(contacts: list[Contact], path: str | Path) -> Path:
    """Write filtered contacts as an explicit ``contacts.npz``, atomically.

    Every frame of each contact's window gets its patch and confidence, so
    :func:`load_external_contacts` followed by :func:`filter_contacts` on the same motion gives
    the same contacts back. It is also a starting point to hand-edit.
    """
    path = Path(path)
    rows = [(f, c.body, p, c.prob) for c in contacts for f in range(c.start, c.stop) for p in c.points]
    arrays = dict(frame=np.array([r[0] for r in rows], dtype=np.int64),
                  body=np.array([r[1] for r in rows], dtype=str),
                  point=np.array([r[2] for r in rows], dtype=float).reshape(-1, 3),
                  prob=np.array([r[3] for r in rows], dtype=float))
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


# --------------------------------------------------------------------------- completion


@dataclass(frozen=True)
class CompletionConfig:
    """:func:`complete_support` settings.

    Attributes:
        support_tolerance: m; a contact point within this distance of an existing box (or of
            the floor plane) rests on it. A contact whose patch mostly rests on the scene needs
            nothing new.
        floor_height: height of the floor plane (the aligned scene puts it at 0); ``None`` when
            only the boxes count.
        cluster_xy: m; patch points link into one surface (single linkage, DBSCAN) when
            their offset lies within the ellipsoid of this horizontal semi-axis and
            ``cluster_height`` along their normal: a walk across a platform chains up, while
            treads a riser apart stay separate.
        cluster_height: m; well below the lowest riser (0.10 m).
        min_contacts: filtered contacts a surface needs (one lone contact is too weak to add
            geometry for); a plane also needs three patch points.
        ransac_threshold: m; inlier distance of the RANSAC plane fit.
        snap_deg: a fitted plane within this angle of level (or of vertical, for a backrest) is
            snapped to it: weight-bearing surfaces in a gravity-aligned scene are level, while a
            seated thigh (whose underside is the seat patch) slopes by up to about 20°.
        top_quantile: the surface goes through this quantile of the inliers' heights above the
            plane: a support lies under the patches, so a low quantile (not the mean) keeps the
            body from sinking into it.
        thickness: m; box thickness (the paper's S_z >= 0.05 m clamp).
        margin: m added on every side of the patches' footprint: patch points lie on the body's
            underside line, and a thigh or foot reaches about this much to either side.
        hinge_distance: m; a box edge this close to the facing side of a perpendicular primitive
            (a chair back, a riser) is extended to meet it.
        hinge_deg: angle tolerance of "perpendicular" and "facing".
        seed: RANSAC seed (runs are reproducible).
    """

    support_tolerance: float = 0.05
    floor_height: float | None = 0.0
    cluster_xy: float = 0.35
    cluster_height: float = 0.04
    min_contacts: int = 2
    ransac_threshold: float = 0.02
    snap_deg: float = 25.0
    top_quantile: float = 0.1
    thickness: float = 0.05
    margin: float = 0.06
    hinge_distance: float = 0.25
    hinge_deg: float = 15.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.thickness < 0.05:
            raise ValueError(f"thickness must be at least 0.05 m (the paper's clamp), got {self.thickness}")
        if self.min_contacts < 1:
            raise ValueError(f"min_contacts must be >= 1, got {self.min_contacts}")


@dataclass(frozen=True)
class SupportRecord:
    """Provenance of one contact box, for ``meta.json``.

    Attributes:
        name: the box's name.
        bodies: bodies whose contacts made it, sorted.
        frames: their most stationary frames, sorted.
        windows: their ``[start, stop)`` frame windows.
    """

    name: str
    bodies: list[str]
    frames: list[int]
    windows: list[list[int]]

    def to_json(self) -> dict:
        """The record as a JSON-ready dict."""
        return {"name": self.name, "bodies": self.bodies, "frames": self.frames, "windows": self.windows}


@dataclass(frozen=True)
class CompletionResult:
    """Output of :func:`complete_support`.

    Attributes:
        boxes: the new boxes only (``source="contact"``, named ``contact_<i>``); the scene is
            ``existing + boxes``.
        records: one :class:`SupportRecord` per new box, same order.
        supported: contacts that already rested on the scene (alone, or as part of a surface
            the scene already has).
        dropped: contacts on surfaces with fewer than ``min_contacts`` contacts.
    """

    boxes: list[Box]
    records: list[SupportRecord]
    supported: int
    dropped: int

    def meta(self) -> list[dict]:
        """The ``meta.json`` entry: each contact primitive with the frames and bodies that support it."""
        return [r.to_json() for r in self.records]


def _supported(points: np.ndarray, boxes: list[Box], cfg: CompletionConfig) -> np.ndarray:
    """(K,) whether each point rests on (or in) an existing box or the floor."""
    near = np.zeros(len(points), dtype=bool)
    if boxes:
        near |= box_signed_distance(points, boxes) <= cfg.support_tolerance
    if cfg.floor_height is not None:
        near |= points[:, 2] <= cfg.floor_height + cfg.support_tolerance
    return near










def _surface_box(points: np.ndarray, hint: np.ndarray, cfg: CompletionConfig, name: str) -> Box:
    """A box whose top face is the RANSAC plane of ``points`` and covers them with the margin."""
    normal, inliers = ransac_height_plane(points, hint, cfg.ransac_threshold, cfg.seed)
    normal = snap_to_gravity(normal, cfg.snap_deg)  # on hint's side already
    frame = plane_frame(normal)
    local = points[inliers] @ frame
    rectangle = min_area_rectangle(local[:, :2])
    centre, half = rectangle.centre, rectangle.half_size
    top = float(np.quantile(local[:, 2], cfg.top_quantile))
    u = frame[:, :2] @ rectangle.axes[0]
    v = np.cross(normal, u)
    rotation = np.stack([u, v, normal], axis=1)
    center = frame[:, :2] @ centre + (top - cfg.thickness / 2) * normal
    return Box(center=center, rotation=rotation, half_size=[half[0] + cfg.margin, half[1] + cfg.margin,
                                                            cfg.thickness / 2],
               source="contact", name=name)


def _hinge(box: Box, others: list[Box], cfg: CompletionConfig) -> Box:
    """Extend ``box`` along its in-plane axes to the facing side of a nearby perpendicular box."""
    center, half = box.center.copy(), box.half_size.copy()
    normal = box.rotation[:, 2]
    cos_tol = math.cos(math.radians(cfg.hinge_deg))
    top = center + half[2] * normal
    for axis in (0, 1):
        for sign in (-1.0, 1.0):
            side = sign * box.rotation[:, axis]
            edge = center + sign * half[axis] * box.rotation[:, axis]
            best = None
            for other in others:
                for k in range(3):
                    face_normal = other.rotation[:, k]
                    if abs(face_normal @ side) < cos_tol:
                        continue
                    face_normal = -np.sign(face_normal @ side) * face_normal  # faces the box
                    face = other.center + other.half_size[k] * face_normal
                    gap = float((face - edge) @ side)
                    if not 0.0 < gap <= cfg.hinge_distance:
                        continue
                    # Where the extended top edge meets the face must lie on that face.
                    meet = top + sign * half[axis] * box.rotation[:, axis] + gap * side
                    rel = np.abs((meet - other.center) @ other.rotation)
                    lateral = [j for j in range(3) if j != k]
                    if np.any(rel[lateral] > other.half_size[lateral] + cfg.support_tolerance):
                        continue
                    if best is None or gap < best:
                        best = gap
            if best is not None:
                half[axis] += best / 2
                center += side * best / 2
    return Box(center=center, rotation=box.rotation, half_size=half, source=box.source, name=box.name)


def complete_support(contacts: list[Contact], boxes: list[Box], cfg: CompletionConfig | None = None
                     ) -> CompletionResult:
    """Boxes for the support surfaces that ``contacts`` imply and ``boxes`` lack.

    Contacts resting mostly on ``boxes`` (or the floor) are skipped; the rest are clustered per
    surface (by horizontal proximity and height along their normal, backrest contacts apart
    from supports below), each surface with at least ``min_contacts`` contacts gets a RANSAC
    plane and a box under it, and the box is extended to meet a perpendicular neighbour
    (:class:`CompletionConfig`).
    """
    cfg = cfg or CompletionConfig()
    supported = 0
    pending: list[Contact] = []
    for c in contacts:
        if _supported(c.points, boxes, cfg).mean() >= 0.5:
            supported += 1
        else:
            pending.append(c)
    new_boxes: list[Box] = []
    records: list[SupportRecord] = []
    dropped = 0
    for is_back in (False, True):
        group = [c for c in pending if (c.part == "back") == is_back]
        if not group:
            continue
        owner = np.concatenate([np.full(len(c.points), i) for i, c in enumerate(group)])
        points = np.concatenate([c.points for c in group])
        normals = np.concatenate([np.broadcast_to(c.normal, c.points.shape) for c in group])
        height = np.einsum("ij,ij->i", points, normals)
        scaled = np.column_stack([points[:, :2] / cfg.cluster_xy, height / cfg.cluster_height])
        labels = DBSCAN(eps=1.0, min_samples=1).fit_predict(scaled)
        # A contact belongs to the surface most of its patch falls on.
        contact_label = np.array([np.bincount(labels[owner == i]).argmax() for i in range(len(group))])
        for label in np.unique(contact_label):
            members = [c for c, lab in zip(group, contact_label) if lab == label]
            if len(members) < cfg.min_contacts or sum(len(c.points) for c in members) < 3:
                dropped += len(members)
                continue
            hint = np.mean([c.normal for c in members], axis=0)
            hint /= np.linalg.norm(hint)
            name = f"contact_{len(new_boxes)}"
            points = np.concatenate([c.points for c in members])
            box = _surface_box(points, hint, cfg, name)
            # The patches as a whole may rest on the scene even where single ones float above
            # it (a pelvis patch over a seat its sloping thighs touch): test the fitted surface.
            normal = box.rotation[:, 2]
            top = box.center @ normal + box.half_size[2]
            if _supported(points - np.outer(points @ normal - top, normal), boxes, cfg).mean() >= 0.5:
                supported += len(members)
                continue
            new_boxes.append(_hinge(box, boxes, cfg))
            records.append(SupportRecord(
                name=name, bodies=sorted({c.body for c in members}), frames=sorted(c.frame for c in members),
                windows=sorted([c.start, c.stop] for c in members)))
    return CompletionResult(boxes=new_boxes, records=records, supported=supported, dropped=dropped)


@dataclass(frozen=True)
class ContactConfig:
    """All settings of contact-guided completion, for the pipeline and its command line.

    Attributes:
        kinematic: cues of :func:`kinematic_contacts`.
        filter: the temporal–kinematic filter (:func:`filter_contacts`).
        completion: support boxes (:func:`complete_support`).
        vertex_quantile: how per-vertex probabilities become a body's (:func:`load_external_contacts`).
    """

    kinematic: KinematicConfig = KinematicConfig()
    filter: FilterConfig = FilterConfig()
    completion: CompletionConfig = CompletionConfig()
    vertex_quantile: float = 0.9
