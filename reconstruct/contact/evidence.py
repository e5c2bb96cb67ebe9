"""Contact sources: per-frame confidence for each of the 24 bodies, from the motion alone
(:func:`kinematic_contacts`) or from a file (:func:`load_external_contacts`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crisp_gym.balance import distance_outside_hull
from crisp_gym.humanoid import BODY_NAMES
from crisp_gym.motion import Motion
from crisp_gym.npz import read_npy, read_npz
from crisp_gym.reconstruct.contact.body_geometry import PARTS, BodyGeometry, body_geometry
from crisp_gym.smpl import SMPL_JOINT_NAMES, SMPL_TO_BODY

NUM_SMPL_VERTICES = 6890
"""Vertices of the SMPL(-H) mesh that InteractVLM's ``pred_contact_3d_smplh`` scores."""


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
