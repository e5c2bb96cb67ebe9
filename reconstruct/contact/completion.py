"""Support completion: boxes under the trusted contacts the scene does not already support, each
topped by the RANSAC plane of its patch and hinged to a perpendicular box it nearly touches."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from sklearn.cluster import DBSCAN

from crisp_gym.geometry import min_area_rectangle, plane_frame, ransac_height_plane, snap_to_gravity
from crisp_gym.humanoid import BODY_NAMES
from crisp_gym.metrics import box_signed_distance
from crisp_gym.reconstruct.contact.body_geometry import BodyGeometry
from crisp_gym.reconstruct.contact.filtering import Contact
from crisp_gym.scene import Box


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


FOOT_PARTNER = {"L_Ankle": "L_Toe", "L_Toe": "L_Ankle", "R_Ankle": "R_Toe", "R_Toe": "R_Ankle"}
"""The other half of each foot: heel and toe bear a foot's weight between them."""


def _foot_rests(contact: Contact, geometry: BodyGeometry, boxes: list[Box], cfg: CompletionConfig) -> bool:
    """Whether ``contact`` is a heel or toe whose whole foot (both halves' patches) mostly rests
    on ``boxes`` over most of the contact's window: a foot on its toes with the heel raised
    stands on the floor, whatever its heel patch alone says."""
    partner = FOOT_PARTNER.get(contact.body)
    if partner is None:
        return False
    window = slice(contact.start, contact.stop)
    sole = np.concatenate([geometry.patches[BODY_NAMES.index(b)][window] for b in (contact.body, partner)], axis=1)
    rests = _supported(sole.reshape(-1, 3), boxes, cfg).reshape(sole.shape[:2]).mean(axis=1) >= 0.5
    return bool(rests.mean() >= 0.5)


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


def complete_support(contacts: list[Contact], boxes: list[Box], cfg: CompletionConfig | None = None,
                     geometry: BodyGeometry | None = None) -> CompletionResult:
    """Boxes for the support surfaces that ``contacts`` imply and ``boxes`` lack.

    Contacts resting mostly on ``boxes`` (or the floor) are skipped, and so, given the motion's
    ``geometry``, are a heel or toe whose whole foot mostly rests on them (a seated foot on its
    toes: its pitched heel patch alone floats); the rest are clustered per
    surface (by horizontal proximity and height along their normal, backrest contacts apart
    from supports below), each surface with at least ``min_contacts`` contacts gets a RANSAC
    plane and a box under it, and the box is extended to meet a perpendicular neighbour
    (:class:`CompletionConfig`).
    """
    cfg = cfg or CompletionConfig()
    supported = 0
    pending: list[Contact] = []
    for c in contacts:
        if _supported(c.points, boxes, cfg).mean() >= 0.5 or (
                geometry is not None and _foot_rests(c, geometry, boxes, cfg)):
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
