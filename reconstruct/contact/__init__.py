"""Human-scene contacts: where they come from, which ones to trust, and the support they imply.

The paper (Sec. 3.3, appendix "Contact-guided scene completion", Algorithm 1 step 4) completes
the scene where the camera never saw the surface a person sat or stood on. Three stages:

1. **Contact sources** (:mod:`~crisp_gym.reconstruct.contact.evidence`) give a per-frame confidence for each of the humanoid's 24 bodies
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

2. **Temporal–kinematic filtering** (:mod:`~crisp_gym.reconstruct.contact.filtering`), the paper's non-maximum
   suppression: a body's contact is kept only where its confidence stays >= τ for L
   consecutive frames while the body's contact patch moves slower than ν, and each such window
   yields its most stationary frame. Windows of a body that lie above a lower window of the same
   body at the same spot a moment before or after are suppressed too: that is an "imminent
   contact" (a foot hovering over a step before it lands), which the paper reports learned
   detectors over-predict and which stillness alone cannot reject.

3. **Support completion** (:mod:`~crisp_gym.reconstruct.contact.completion`): the filtered contact patches not already
   resting on the scene are clustered per surface, a plane is fitted with RANSAC, and a box
   (``source="contact"``) is made whose top is that plane and whose footprint covers the patches
   with a margin; it is extended to a perpendicular primitive it nearly touches (a seat to its
   chair back, a platform top to its riser).

A body's *contact patch* is a few world points on the part of the humanoid that touches a
support (:mod:`~crisp_gym.reconstruct.contact.body_geometry`): the four corners and centre of the lowest face of a foot or
hand box; the underside of the proximal half of a thigh; the back side of a trunk segment; the
underside of any other capsule. The humanoid has no buttocks (its pelvis capsule rides about
10 cm above where a person's buttocks meet a seat), so the pelvis patch is its capsule axis
dropped to the level of the thighs' undersides at the hips.

:func:`contact_completion` runs the three stages with a :class:`ContactConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

from crisp_gym.motion import Motion
from crisp_gym.reconstruct.contact.body_geometry import PART_OF, PARTS, BodyGeometry, body_geometry
from crisp_gym.reconstruct.contact.completion import (
    CompletionConfig,
    CompletionResult,
    SupportRecord,
    complete_support,
)
from crisp_gym.reconstruct.contact.evidence import (
    NUM_SMPL_VERTICES,
    ContactEvidence,
    KinematicConfig,
    kinematic_contacts,
    load_external_contacts,
)
from crisp_gym.reconstruct.contact.filtering import (
    Contact,
    FilterConfig,
    PartFilter,
    contact_labels,
    filter_contacts,
    save_contacts,
)
from crisp_gym.scene import Box

ContactSource = Literal["kinematic", "none"] | Path
"""``"kinematic"`` (from the motion), ``"none"``, or a contacts file (see :func:`load_external_contacts`)."""

__all__ = [
    "NUM_SMPL_VERTICES", "PARTS", "PART_OF", "BodyGeometry", "CompletionConfig", "CompletionResult", "Contact",
    "ContactConfig", "ContactEvidence", "ContactSource", "FilterConfig", "KinematicConfig", "PartFilter",
    "SupportRecord", "body_geometry", "complete_support", "contact_completion", "contact_labels",
    "filter_contacts", "kinematic_contacts", "load_external_contacts", "save_contacts",
]


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


def contact_completion(motion: Motion, boxes: list[Box], source: ContactSource, cfg: ContactConfig,
                       vertex_map: Path | None = None) -> CompletionResult | None:
    """Supports the motion's contacts need and ``boxes`` lack (``None`` for ``source="none"``)."""
    if isinstance(source, str) and source == "none":
        return None
    geometry = body_geometry(motion)
    if isinstance(source, str) and source == "kinematic":
        evidence = kinematic_contacts(motion, cfg.kinematic, geometry)
    else:
        evidence = load_external_contacts(source, motion, vertex_map, cfg.vertex_quantile)
    contacts = filter_contacts(evidence, motion, cfg.filter, geometry)
    # The clip's scene is only its boxes: the aligned z = 0 holds the humanoid only where a floor
    # box covers it. Floor contacts that the seen floor does not cover (the view cut it off, or
    # only a far patch of floor was seen) must build their support like any other unseen surface.
    return complete_support(contacts, boxes, replace(cfg.completion, floor_height=None), geometry)
