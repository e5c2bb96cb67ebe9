"""From per-body world rotations to a humanoid motion a body can stand on.

Every retargeter (BVH rotations in :mod:`crisp_gym.bvh`, video landmarks in
:mod:`crisp_gym.reconstruct.landmarks`) first finds each of the 24 bodies' world orientation and the
pelvis position per frame; what follows is shared: local hinge angles, the noisy hands
low-passed, planted feet laid flat (:func:`~crisp_gym.motion.level_feet`), joints fitted into
the humanoid's ranges with the feet kept in place (:func:`~crisp_gym.motion.fit_into_range`),
and the planted feet put on the floor frame by frame (:func:`~crisp_gym.motion.ground_stance`)
or by one offset (:func:`~crisp_gym.motion.ground`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES, PARENTS, build_humanoid, hinge_ranges
from crisp_gym.motion import (
    Motion,
    StanceGrounding,
    fit_into_range,
    ground,
    ground_stance,
    level_feet,
    low_pass_joints,
    range_fit_change,
    rotations_to_hinge_angles,
)

log = logging.getLogger(__name__)

FLICKERING_BODIES: tuple[str, ...] = ("L_Elbow", "R_Elbow", "L_Wrist", "R_Wrist", "L_Hand", "R_Hand")
"""Bodies whose captured rotations are low-passed on import: hand markers are the noisiest."""


@dataclass(frozen=True)
class Retargeted:
    """A retargeted motion and what was done to it.

    Attributes:
        motion: the humanoid motion, grounded.
        clipped_fraction: share of hinge values changed to fit the joints into the humanoid's ranges.
        max_clip_deg: the largest turn of a joint that fitting into range caused, in degrees.
        ground_offset: (T,) metres added to each frame's root height to put the feet on the floor.
    """

    motion: Motion
    clipped_fraction: float
    max_clip_deg: float
    ground_offset: np.ndarray


def motion_from_rotations(body_rotations: np.ndarray, root_pos: np.ndarray, fps: float, *,
                          model: mujoco.MjModel | None = None,
                          grounding: StanceGrounding | None = StanceGrounding(),
                          clip_to_range: bool = True, low_pass_hz: float | None = 6.0,
                          shift: bool = True) -> Retargeted:
    """The motion whose bodies have world rotations ``body_rotations`` ((T, 24, 3, 3), in
    :data:`~crisp_gym.humanoid.BODY_NAMES` order, identity = our T-pose) and pelvis at ``root_pos``.

    ``low_pass_hz`` low-passes the hinge angles of :data:`FLICKERING_BODIES` (``None``: as given);
    ``grounding`` lays planted feet flat and grounds them per frame (``None``: one offset for
    the whole motion, feet as given); ``shift=False`` lays the feet flat but moves nothing up or
    down (for a caller that has put the feet on the floor itself); ``model`` is the humanoid
    grounded on (default: 1.70 m). ``clip_to_range`` fits the joints into the humanoid's ranges
    (:func:`~crisp_gym.motion.fit_into_range`; ``False``: hinges as decomposed).
    """
    t = len(body_rotations)
    ranges = hinge_ranges().reshape(-1, 3, 2)
    index = {body: i for i, body in enumerate(BODY_NAMES)}
    local = np.empty_like(body_rotations)
    for i, body in enumerate(BODY_NAMES):
        parent = PARENTS[body]
        glob = body_rotations[:, i]
        local[:, i] = glob if parent is None else np.swapaxes(body_rotations[:, index[parent]], 1, 2) @ glob
    motion = Motion(fps=fps, root_pos=root_pos,
                    root_quat=Rotation.from_matrix(body_rotations[:, 0]).as_quat(scalar_first=True),
                    dof_pos=rotations_to_hinge_angles(local[:, 1:], ranges if clip_to_range else None).reshape(t, -1))
    if low_pass_hz is not None:
        motion = low_pass_joints(motion, low_pass_hz, FLICKERING_BODIES)
    model = model if model is not None else build_humanoid()
    if grounding is not None:
        motion = level_feet(motion, model, grounding)
    clipped_fraction, max_clip = 0.0, 0.0
    if clip_to_range:
        angles = motion.dof_pos
        motion = fit_into_range(motion, model)
        clipped_fraction, max_clip = range_fit_change(angles, motion.dof_pos)
    if not shift:
        grounded = motion
    elif grounding is None:
        grounded = ground(motion, model)
    else:
        grounded = ground_stance(motion, model, grounding)
    if clipped_fraction > 0:
        log.info("retarget fitted %.2f%% of hinge values into range (joints turned by at most %.1f deg)",
                 100 * clipped_fraction, max_clip)
    return Retargeted(grounded, clipped_fraction, max_clip, grounded.root_pos[:, 2] - motion.root_pos[:, 2])
