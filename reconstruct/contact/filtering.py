"""The temporal–kinematic filter (the paper's non-maximum suppression): which contacts to trust,
one per still window, without the imminent contacts of a foot hovering before it lands."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crisp_gym.atomic import atomic_path
from crisp_gym.humanoid import BODY_NAMES
from crisp_gym.motion import Motion
from crisp_gym.reconstruct.contact.body_geometry import PART_OF, UP, BodyGeometry, body_geometry
from crisp_gym.reconstruct.contact.evidence import ContactEvidence


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
            normal = geo.forward[frame] if part == "back" else UP
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
