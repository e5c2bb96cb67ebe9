"""ProtoMotions ``.motion`` files: a torch-saved dict of per-frame arrays on the SMPL humanoid.

ProtoMotions' SMPL humanoid has this project's 24 bodies and 69 hinges, with the same names and
order (the pelvis first, then depth first; each body's x, y, z hinges). A ``.motion`` file holds:

======================  ===========================================================================
key                     content
======================  ===========================================================================
``dof_pos``             (T, 69) hinge angles (rad) in :data:`crisp_gym.humanoid.DOF_NAMES` order
``rigid_body_pos``      (T, 24, 3) world positions (m, z up) in :data:`crisp_gym.humanoid.BODY_NAMES` order
``rigid_body_rot``      (T, 24, 4) world orientations, quaternions **x y z w** (Isaac Gym's order)
``fps``                 frames per second
``rigid_body_contacts`` (T, 24), optional: which bodies touch the ground
velocities              ``dof_vel``, ``rigid_body_vel``, ``rigid_body_ang_vel``: not needed (derived)
======================  ===========================================================================

The file is read with ``torch.load(weights_only=True)``: tensors and plain values only, no code.
The hinge angles must reproduce the file's own body orientations on this humanoid (median error
under :data:`MAX_ORIENTATION_ERROR_DEG`), which checks the conventions above on every file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, build_humanoid
from crisp_gym.motion import Motion, compute_kinematics
from crisp_gym.torch_file import load_tensors

REQUIRED = ("dof_pos", "rigid_body_pos", "rigid_body_rot", "fps")
MAX_ORIENTATION_ERROR_DEG = 2.0
"""Median angle between the body orientations the hinges give and the file's own, beyond which the
file's conventions are not the expected ones (float32 storage gives hundredths of a degree)."""


def _array(value) -> np.ndarray:
    """A tensor, array or number as a float array."""
    return np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value, dtype=float)


def read_protomotions(path: str | Path) -> Motion:
    """The :class:`Motion` of a ProtoMotions ``.motion`` file (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no motion file at {path}")
    content = load_tensors(path)
    if not isinstance(content, dict) or not set(REQUIRED) <= set(content):
        found = sorted(content) if isinstance(content, dict) else type(content).__name__
        raise ValueError(f"{path} is not a ProtoMotions motion: expected a dict with {list(REQUIRED)}, got {found}")
    dof_pos, body_pos, body_rot = (_array(content[k]) for k in ("dof_pos", "rigid_body_pos", "rigid_body_rot"))
    t = dof_pos.shape[0] if dof_pos.ndim == 2 else -1
    expected = {"dof_pos": (t, len(DOF_NAMES)), "rigid_body_pos": (t, len(BODY_NAMES), 3),
                "rigid_body_rot": (t, len(BODY_NAMES), 4)}
    for key, value in zip(expected, (dof_pos, body_pos, body_rot)):
        if value.shape != expected[key]:
            raise ValueError(f"{path}: {key} must have shape (T, {', '.join(map(str, expected[key][1:]))}) on the "
                             f"SMPL humanoid (T shared), got {value.shape}")
    fps = _array(content["fps"]).reshape(-1)
    if fps.size != 1:
        raise ValueError(f"{path}: fps must be one number, got {content['fps']!r}")
    contacts = None
    if "rigid_body_contacts" in content:
        contacts = _array(content["rigid_body_contacts"]) > 0.5
        if contacts.shape != (t, len(BODY_NAMES)):
            raise ValueError(f"{path}: rigid_body_contacts must have shape (T, {len(BODY_NAMES)}), "
                             f"got {contacts.shape}")
    body_quat = body_rot[..., [3, 0, 1, 2]]  # x y z w -> w x y z
    motion = Motion(fps=float(fps[0]), root_pos=body_pos[:, 0], root_quat=body_quat[:, 0], dof_pos=dof_pos,
                    dof_names=DOF_NAMES, contacts=contacts)
    _check_conventions(path, motion, body_quat)
    return motion


def _check_conventions(path: Path, motion: Motion, body_quat: np.ndarray) -> None:
    """ValueError unless the hinges, composed on our humanoid, give the file's own body orientations
    (a check of the conventions that body proportions, which differ per subject, do not affect)."""
    kin = compute_kinematics(motion, build_humanoid())
    error = (Rotation.from_quat(kin.body_quat.reshape(-1, 4), scalar_first=True).inv()
             * Rotation.from_quat(body_quat.reshape(-1, 4), scalar_first=True)).magnitude()
    median = float(np.degrees(np.median(error)))
    if median > MAX_ORIENTATION_ERROR_DEG:
        raise ValueError(f"{path}: its hinge angles put the bodies {median:.0f}° (median) away from its own "
                         f"rigid_body_rot; the file's conventions (hinge order, quaternion order x y z w, body "
                         f"frames) are not the SMPL humanoid's this reader expects")
