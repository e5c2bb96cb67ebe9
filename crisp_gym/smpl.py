"""SMPL pose parameters (axis-angle ``global_orient``, ``body_pose``, ``transl``) <-> :class:`Motion`.

Three layouts of the same parameters are read: SMPL's own (``global_orient`` (T,3),
``body_pose`` (T,69 or T,63), ``transl``), AMASS's (``poses`` (T,72) SMPL, (T,156) SMPL-H or
(T,165) SMPL-X, of which the root and the 21 body joints are used; ``trans``;
``mocap_framerate``; z-up) and the PHC / SMPLSim one (``pose_aa`` (T,24,3), ``trans``). Entries
that would need pickles to load (AMASS's ``gender`` is sometimes one) are skipped: none is used.

SMPL's joints map to our bodies by name (:data:`SMPL_TO_BODY`); its body frame (y up,
facing +z, x to the body's left) becomes ours (z up, facing +x, left +y) by the fixed
change of basis :data:`SMPL_TO_OURS` applied to every local rotation (``C R Cᵀ``). Both
skeletons rest in the same T-pose, so no further rest alignment is needed.

``transl`` is not the pelvis position: SMPL puts the pelvis at ``transl + J0(betas)``, with
``J0`` the shape-dependent rest pelvis joint (about 0.22 m below the model origin for the
mean shape). Without the shape we take ``transl`` as the pelvis and then ground the motion
(feet on z = 0), which removes the vertical part of that constant offset; its horizontal
part (a few cm for y-up inputs) is left in, shifting the whole path by a constant.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from crisp_gym.atomic import atomic_path
from crisp_gym.humanoid import BODY_NAMES, build_humanoid
from crisp_gym.motion import Motion, ground, hinge_angles_to_rotations, rotations_to_hinge_angles
from crisp_gym.npz import read_npz

SMPL_JOINT_NAMES: tuple[str, ...] = (
    "Pelvis", "L_Hip", "R_Hip", "Spine1", "L_Knee", "R_Knee", "Spine2", "L_Ankle", "R_Ankle",
    "Spine3", "L_Foot", "R_Foot", "Neck", "L_Collar", "R_Collar", "Head", "L_Shoulder",
    "R_Shoulder", "L_Elbow", "R_Elbow", "L_Wrist", "R_Wrist", "L_Hand", "R_Hand",
)  # fmt: skip
"""SMPL's 24 joints in its (breadth-first) order; ``body_pose`` holds the last 23."""

_RENAMED = {"Spine1": "Torso", "Spine2": "Spine", "Spine3": "Chest", "L_Foot": "L_Toe", "R_Foot": "R_Toe",
            "L_Collar": "L_Thorax", "R_Collar": "R_Thorax"}
SMPL_TO_BODY: dict[str, str] = {j: _RENAMED.get(j, j) for j in SMPL_JOINT_NAMES}
"""SMPL joint name -> our body name."""

SMPL_TO_OURS = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""Rotation taking SMPL body axes (x left, y up, z forward) to ours (x forward, y left, z up)."""

_BODY_INDEX = [SMPL_JOINT_NAMES.index(next(j for j, b in SMPL_TO_BODY.items() if b == body))
               for body in BODY_NAMES]  # SMPL index of each of our bodies


def _world_to_ours(up_axis: str) -> np.ndarray:
    """Rotation from the input's world axes to ours."""
    if up_axis == "y":
        return SMPL_TO_OURS
    if up_axis == "z":
        return np.eye(3)
    raise ValueError(f"up_axis must be 'y' (SMPL's own world), 'z' (already z-up) or 'auto', got {up_axis!r}")


UP_AXES = ("y", "z")
"""World up axes of SMPL inputs: ``y`` (SMPL's own world) or ``z`` (AMASS, PHC)."""


def read_smpl_source(source: str | Path | Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The arrays of SMPL parameters: an npz path (entries that need pickles skipped) or a dict."""
    if isinstance(source, Mapping):
        return {k: np.asarray(v) for k, v in source.items()}
    return read_npz(source, "SMPL parameter file (global_orient, body_pose, transl or AMASS poses, trans)",
                    skip_objects=True)


_AMASS_WIDTHS = (72, 156, 165)


def _standard_keys(params: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``params`` with the AMASS (``poses``, ``trans``) or PHC (``pose_aa``, ``trans``) layout
    renamed to SMPL's ``global_orient``, ``body_pose``, ``transl``."""
    out = dict(params)
    if "transl" not in out and "trans" in out:
        out["transl"] = out["trans"]
    if "global_orient" in out or "body_pose" in out:
        return out
    if "pose_aa" in out:
        pose = np.asarray(out["pose_aa"])
        if pose.ndim != 3 or pose.shape[1:] != (24, 3):
            raise ValueError(f"SMPL pose_aa must have shape (T, 24, 3), got {pose.shape}")
        out["global_orient"], out["body_pose"] = pose[:, 0], pose[:, 1:].reshape(len(pose), 69)
    elif "poses" in out:
        pose = np.asarray(out["poses"])
        if pose.ndim != 2 or pose.shape[1] not in _AMASS_WIDTHS:
            raise ValueError(f"AMASS poses must have shape (T, 72) (SMPL), (T, 156) (SMPL-H) or (T, 165) "
                             f"(SMPL-X), got {pose.shape}")
        # SMPL's 23 joints; SMPL-H and SMPL-X have 21 body joints then jaw, eyes and fingers.
        out["global_orient"], out["body_pose"] = pose[:, :3], pose[:, 3:72 if pose.shape[1] == 72 else 66]
    return out



def _real_array(value: object, key: str) -> np.ndarray:
    """``value`` as a float array; a complex or non-numeric one is a damaged file, not cast."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"SMPL {key} must be a real numeric array, got dtype {arr.dtype}")
    return arr.astype(float)


def detect_up_axis(params: Mapping[str, np.ndarray]) -> tuple[str, dict[str, float]]:
    """The world up axis of SMPL parameters (:data:`UP_AXES`), and per axis the mean
    uprightness it gives (the pelvis' up axis dotted with the world's, -1..1).

    The axis that keeps the pelvis most upright over the clip wins: people stand, walk, sit
    and squat with the pelvis upright; only a clip spent lying down leaves it ambiguous.
    """
    orient = _real_array(_standard_keys(params).get("global_orient", np.zeros((0, 3))), "global_orient")
    if orient.ndim != 2 or orient.shape[1] != 3 or not len(orient) or not np.isfinite(orient).all():
        raise ValueError("the up axis is detected from global_orient (T, 3) finite values; "
                         f"got {orient.shape}")
    pelvis_up = Rotation.from_rotvec(orient).as_matrix() @ SMPL_TO_OURS.T[:, 2]  # the body's up in the file's world
    score = {axis: float((_world_to_ours(axis) @ pelvis_up.T)[2].mean()) for axis in UP_AXES}
    return max(score, key=score.get), score


def _checked(params: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T,3) global_orient, (T,23,3) body_pose, (T,3) transl, validated."""
    params = _standard_keys(params)
    missing = [k for k in ("global_orient", "body_pose", "transl") if k not in params]
    if missing:
        raise ValueError(f"SMPL parameters lack {missing}; expected global_orient (T,3), "
                         f"body_pose (T,63 or T,69), transl (T,3); got keys {sorted(params)}")
    orient, pose, transl = (_real_array(params[k], k) for k in ("global_orient", "body_pose", "transl"))
    t = orient.shape[0] if orient.ndim == 2 else -1
    if pose.ndim == 3 and pose.shape[2] == 3:
        pose = pose.reshape(pose.shape[0], -1)
    for key, arr, widths in (("global_orient", orient, (3,)), ("body_pose", pose, (63, 69)),
                             ("transl", transl, (3,))):
        if arr.ndim != 2 or arr.shape[0] != t or arr.shape[1] not in widths:
            want = " or ".join(f"(T, {w})" for w in widths)
            raise ValueError(f"SMPL {key} must have shape {want} with T shared by all three, "
                             f"got {arr.shape} (global_orient is {orient.shape})")
        bad = ~np.isfinite(arr)
        if bad.any():
            raise ValueError(f"SMPL {key} has non-finite values (first at frame {int(np.argwhere(bad)[0, 0])})")
    if t < 2:
        raise ValueError(f"a motion needs at least 2 frames, got {t}")
    if pose.shape[1] == 63:  # SMPL-X / SMPL-H style bodies: no hand joints, keep them at rest
        pose = np.concatenate([pose, np.zeros((t, 6))], axis=1)
    return orient, pose.reshape(t, 23, 3), transl


def stored_fps(params: Mapping[str, np.ndarray]) -> float | None:
    """The frame rate SMPL parameters carry (``fps`` or AMASS's ``mocap_framerate``), if any."""
    for key in ("fps", "mocap_framerate"):
        if key in params:
            value = np.asarray(params[key])
            if value.size != 1 or not np.issubdtype(value.dtype, np.number):
                raise ValueError(f"SMPL {key} must be one number, got {value!r}")
            return float(value.reshape(()))
    return None


def load_smpl_params(source: str | Path | Mapping[str, np.ndarray], *, fps: float | None = None,
                     up_axis: str = "y", to_floor: bool = True,
                     model: mujoco.MjModel | None = None) -> Motion:
    """A humanoid :class:`Motion` from SMPL axis-angle parameters (an npz path or a dict) in
    any layout of the module docstring.

    ``fps`` defaults to the source's ``fps`` or ``mocap_framerate`` entry, else 30.
    ``up_axis="y"`` is SMPL's own world (y up); ``"z"`` means the world is already z-up and
    only the body frame is converted; ``"auto"`` takes :func:`detect_up_axis`'s choice.
    ``to_floor`` grounds the result on ``model`` (the default humanoid when ``None``) by one
    offset; see the module docstring for how ``transl`` is treated.
    """
    params = read_smpl_source(source)
    if up_axis == "auto":
        up_axis, _ = detect_up_axis(params)
    world = _world_to_ours(up_axis)
    if fps is None:
        fps = stored_fps(params) or 30.0
    orient, pose, transl = _checked(params)
    t = orient.shape[0]
    rotvecs = np.concatenate([orient[:, None], pose], axis=1)  # (T, 24, 3) in SMPL order
    local = Rotation.from_rotvec(rotvecs.reshape(-1, 3)).as_matrix().reshape(t, 24, 3, 3)
    local = local[:, _BODY_INDEX]  # our body order
    c = SMPL_TO_OURS
    root = world @ local[:, 0] @ c.T
    joints = c @ local[:, 1:] @ c.T
    motion = Motion(fps=fps, root_pos=transl @ world.T,
                    root_quat=Rotation.from_matrix(root).as_quat(scalar_first=True),
                    dof_pos=rotations_to_hinge_angles(joints).reshape(t, -1))
    if to_floor:
        motion = ground(motion, model if model is not None else build_humanoid())
    return motion


def save_smpl_params(motion: Motion, path: str | Path) -> Path:
    """Write ``motion`` as SMPL parameters (y-up world, ``body_pose`` (T, 69)) plus ``fps``.

    ``transl`` is the pelvis position, as :func:`load_smpl_params` reads it. Written atomically.
    """
    return write_smpl_npz(path, motion, frame=SMPL_TO_OURS.T)


def write_smpl_npz(path: str | Path, motion: Motion, frame: np.ndarray | None = None,
                   pelvis_offset: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Path:
    """Write ``motion`` as SMPL parameters, atomically: ``global_orient`` (T, 3) and ``body_pose``
    (T, 69) axis-angle, ``transl`` (T, 3) and ``fps``.

    ``frame`` (3, 3) rotates the motion's world into the file's (identity: keep it, e.g. a camera
    frame); ``transl`` is the pelvis position there minus ``pelvis_offset`` (SMPL's ``transl`` is
    the body model's origin, not its pelvis, for readers that run the body model).
    """
    frame = np.eye(3) if frame is None else np.asarray(frame, dtype=float)
    m = motion.in_humanoid_order()
    t = m.num_frames
    c = SMPL_TO_OURS
    local = np.empty((t, len(BODY_NAMES), 3, 3))
    local[:, 0] = frame @ Rotation.from_quat(m.root_quat, scalar_first=True).as_matrix() @ c
    local[:, 1:] = c.T @ hinge_angles_to_rotations(m.dof_pos.reshape(t, -1, 3)) @ c
    smpl_order = np.empty_like(local)
    smpl_order[:, _BODY_INDEX] = local
    rotvecs = Rotation.from_matrix(smpl_order.reshape(-1, 3, 3)).as_rotvec().reshape(t, 24, 3)
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, global_orient=rotvecs[:, 0], body_pose=rotvecs[:, 1:].reshape(t, 69),
                 transl=m.root_pos @ frame.T - np.asarray(pelvis_offset, dtype=float), fps=np.float64(m.fps))
    return path
