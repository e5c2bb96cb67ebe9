"""Motion export in the layouts other stacks read, each with a reader for the round trip.

All positions in metres (z up), angles in radians, the motion's own frame rate unless stated.
Quaternions are written in the order asked for (``"wxyz"``, MuJoCo / Isaac Lab / Genesis, or
``"xyzw"``, Isaac Gym / PyBullet / SciPy), and every file states it, in its column names or a
``quat_order`` entry. Joints are always named; readers reorder by name.

=================  ==================================================================================
layout             content
=================  ==================================================================================
CSV                one row per frame: ``frame, time, root_pos_{x,y,z}``, ``root_quat_*`` in the
                   chosen order, then the 69 hinge angles under their names
``fields`` npz     ``fps``, ``quat_order``; ``root_pos`` (T,3), ``root_rot`` (T,4), ``root_lin_vel``,
                   ``root_ang_vel`` (T,3, world frame); ``dof_pos``, ``dof_vel`` (T,69) with
                   ``dof_names``; ``body_pos`` (T,24,3), ``body_rot`` (T,24,4) world poses with
                   ``body_names`` (the Isaac Gym / ProtoMotions style of per-field arrays)
``qpos`` npz       ``fps``; MuJoCo's ``qpos`` (T,76: root position, w x y z quaternion, hinges) and
                   ``qvel`` (T,75: world linear, body-frame angular velocity, hinge rates) with
                   ``qpos_names``/``qvel_names`` (LocoMuJoCo / MuJoCo Playground style)
``smpl`` npz       ``pose_aa`` (T,24,3) axis-angle per SMPL joint (SMPL's joint order, names in
                   ``joint_names``), ``trans`` (T,3) the pelvis position, ``fps`` = 30, ``up_axis``
                   (PHC / SMPLSim style; ``pose_aa.reshape(T, 72)`` is their flat layout)
``amass`` npz      ``poses`` (T,72) axis-angle (root then SMPL's 23 joints, SMPL's order), ``trans``
                   (T,3) the pelvis position in a z-up world, ``betas`` (16,) zeros, ``gender``
                   ``"neutral"``, ``mocap_framerate`` = 30 (the AMASS file the ProtoMotions and PHC
                   converters read)
``beyondmimic``    ``fps`` (1,); ``joint_pos``, ``joint_vel`` (T,69) in ``joint_names`` order;
npz                ``body_pos_w``, ``body_quat_w`` (w x y z), ``body_lin_vel_w``, ``body_ang_vel_w``
                   (T,24,·, world frame) in ``body_names`` order, the pelvis (root) first; the
                   motion's own frame rate (BeyondMimic / mjlab motion tracking)
=================  ==================================================================================

``root_rot`` is deliberately not named ``root_quat``: :meth:`crisp_gym.motion.Motion.load` refuses
the file instead of silently reading an ``xyzw`` quaternion as ``wxyz``.

SMPL and AMASS: our bodies map to SMPL's joints by name and our body axes to SMPL's by the fixed
basis change of :mod:`crisp_gym.smpl`; ``trans`` is the pelvis position (SMPL adds a shape-dependent
offset that only the user's betas define: with the zero ``betas`` written, an SMPL body model puts
its pelvis about 0.22 m off ``trans``, mostly along the body's up axis), so
:func:`crisp_gym.smpl.load_smpl_params` reads the files back.
"""

from __future__ import annotations

import csv
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from crisp_gym.atomic import atomic_path
from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, HumanoidConfig, build_humanoid
from crisp_gym.motion import Motion, compute_kinematics, hinge_angles_to_rotations
from crisp_gym.npz import read_npz
from crisp_gym.smpl import SMPL_JOINT_NAMES, SMPL_TO_BODY, SMPL_TO_OURS

QUAT_ORDERS = ("wxyz", "xyzw")
NPZ_LAYOUTS = ("fields", "qpos", "smpl", "amass", "beyondmimic")
SMPL_FPS = 30.0
"""Frame rate of the SMPL layout (the rate of the AMASS-derived data the SMPL trackers train on)."""

_AXES = ("x", "y", "z")


def _check_order(quat_order: str) -> None:
    if quat_order not in QUAT_ORDERS:
        raise ValueError(f"quat_order must be one of {QUAT_ORDERS}, got {quat_order!r}")


def to_order(quat_wxyz: np.ndarray, quat_order: str) -> np.ndarray:
    """Quaternions (…, 4) w x y z reordered to ``quat_order``."""
    _check_order(quat_order)
    return quat_wxyz if quat_order == "wxyz" else np.roll(quat_wxyz, -1, axis=-1)


def from_order(quat: np.ndarray, quat_order: str) -> np.ndarray:
    """Quaternions (…, 4) in ``quat_order`` reordered to w x y z."""
    _check_order(quat_order)
    return quat if quat_order == "wxyz" else np.roll(quat, 1, axis=-1)


# ------------------------------------------------------------------------------------------------
# CSV


def csv_columns(quat_order: str = "wxyz") -> list[str]:
    """The CSV header: frame, time, root position, root quaternion in ``quat_order``, hinge names."""
    _check_order(quat_order)
    return (["frame", "time"] + [f"root_pos_{a}" for a in _AXES]
            + [f"root_quat_{c}" for c in quat_order] + list(DOF_NAMES))


def write_motion_csv(motion: Motion, path: str | Path, quat_order: str = "wxyz") -> Path:
    """One row per frame (see :func:`csv_columns`), numbers at full precision; written atomically."""
    m = motion.in_humanoid_order()
    frames = np.arange(m.num_frames)
    rows = np.column_stack([frames, frames / m.fps, m.root_pos, to_order(m.root_quat, quat_order), m.dof_pos])
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(csv_columns(quat_order))
        writer.writerows([[int(r[0]), *(repr(float(v)) for v in r[1:])] for r in rows])
    return Path(path)


def read_motion_csv(path: str | Path) -> Motion:
    """A :class:`Motion` from a CSV of :func:`write_motion_csv` (either quaternion order; fps from ``time``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no motion CSV at {path}")
    with open(path, newline="") as f:
        header = next(csv.reader(f), [])
    columns = {name: i for i, name in enumerate(header)}
    needed = ["time"] + [f"root_pos_{a}" for a in _AXES] + [f"root_quat_{c}" for c in "wxyz"] + list(DOF_NAMES)
    missing = [n for n in needed if n not in columns]
    if missing:
        raise ValueError(f"{path} lacks the columns {missing[:6]}; expected a header like {csv_columns()[:8]}...")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if data.shape[0] < 2:
        raise ValueError(f"{path} needs at least 2 frames, got {data.shape[0]}")
    pick = lambda names: data[:, [columns[n] for n in names]]
    time = data[:, columns["time"]]
    return Motion(fps=(len(time) - 1) / (time[-1] - time[0]), root_pos=pick([f"root_pos_{a}" for a in _AXES]),
                  root_quat=pick([f"root_quat_{c}" for c in "wxyz"]), dof_pos=pick(DOF_NAMES))


# ------------------------------------------------------------------------------------------------
# npz layouts


def fields_layout(motion: Motion, quat_order: str = "wxyz", model: mujoco.MjModel | None = None) -> dict:
    """The ``fields`` arrays (module docstring); body poses by forward kinematics on ``model``."""
    m = motion.in_humanoid_order()
    kin = compute_kinematics(m, model if model is not None else build_humanoid(HumanoidConfig()))
    qvel = m.qvel()
    root_rot = Rotation.from_quat(m.root_quat, scalar_first=True)
    return {
        "fps": np.float64(m.fps), "quat_order": np.array(quat_order),
        "root_pos": m.root_pos, "root_rot": to_order(m.root_quat, quat_order),
        "root_lin_vel": qvel[:, :3], "root_ang_vel": root_rot.apply(qvel[:, 3:6]),
        "dof_pos": m.dof_pos, "dof_vel": qvel[:, 6:], "dof_names": np.array(DOF_NAMES),
        "body_pos": kin.body_pos, "body_rot": to_order(kin.body_quat, quat_order), "body_names": np.array(BODY_NAMES),
    }


def qpos_layout(motion: Motion) -> dict:
    """The ``qpos`` arrays (module docstring)."""
    m = motion.in_humanoid_order()
    root = ["root_pos_x", "root_pos_y", "root_pos_z"]
    return {
        "fps": np.float64(m.fps), "qpos": m.qpos(), "qvel": m.qvel(),
        "qpos_names": np.array(root + [f"root_quat_{c}" for c in "wxyz"] + list(DOF_NAMES)),
        "qvel_names": np.array(["root_lin_vel_x", "root_lin_vel_y", "root_lin_vel_z",
                                "root_ang_vel_x", "root_ang_vel_y", "root_ang_vel_z"] + list(DOF_NAMES)),
    }


def _smpl_world(up_axis: str) -> np.ndarray:
    """Rotation from the SMPL file's world axes to ours."""
    if up_axis == "z":
        return np.eye(3)
    if up_axis == "y":
        return SMPL_TO_OURS
    raise ValueError(f"up_axis must be 'z' (AMASS, PHC) or 'y' (SMPL's own world), got {up_axis!r}")


def smpl_layout(motion: Motion, up_axis: str = "z") -> dict:
    """The ``smpl`` arrays (module docstring), resampled to :data:`SMPL_FPS`."""
    world = _smpl_world(up_axis)
    m = motion.in_humanoid_order().resample(SMPL_FPS)
    t = m.num_frames
    c = SMPL_TO_OURS
    local = np.empty((t, len(BODY_NAMES), 3, 3))
    # Ours = world · smpl · cᵀ for the root and c · smpl · cᵀ for the joints (crisp_gym.smpl), inverted here.
    local[:, 0] = world.T @ Rotation.from_quat(m.root_quat, scalar_first=True).as_matrix() @ c
    local[:, 1:] = c.T @ hinge_angles_to_rotations(m.dof_pos.reshape(t, -1, 3)) @ c
    order = [BODY_NAMES.index(SMPL_TO_BODY[j]) for j in SMPL_JOINT_NAMES]
    pose_aa = Rotation.from_matrix(local[:, order].reshape(-1, 3, 3)).as_rotvec().reshape(t, 24, 3)
    return {"pose_aa": pose_aa, "trans": m.root_pos @ world, "fps": np.float64(SMPL_FPS),
            "joint_names": np.array(SMPL_JOINT_NAMES), "up_axis": np.array(up_axis)}


def amass_layout(motion: Motion) -> dict:
    """The ``amass`` arrays (module docstring), resampled to :data:`SMPL_FPS`."""
    smpl = smpl_layout(motion, "z")
    t = smpl["pose_aa"].shape[0]
    return {"poses": smpl["pose_aa"].reshape(t, 72), "trans": smpl["trans"], "betas": np.zeros(16),
            "gender": np.array("neutral"), "mocap_framerate": np.float64(SMPL_FPS)}


def beyondmimic_layout(motion: Motion, model: mujoco.MjModel | None = None) -> dict:
    """The ``beyondmimic`` arrays (module docstring); body states by forward kinematics on ``model``."""
    m = motion.in_humanoid_order()
    kin = compute_kinematics(m, model if model is not None else build_humanoid(HumanoidConfig()))
    return {
        "fps": np.array([m.fps]), "joint_pos": m.dof_pos, "joint_vel": m.qvel()[:, 6:],
        "joint_names": np.array(DOF_NAMES), "body_names": np.array(BODY_NAMES),
        "body_pos_w": kin.body_pos, "body_quat_w": kin.body_quat,
        "body_lin_vel_w": kin.body_lin_vel, "body_ang_vel_w": kin.body_ang_vel,
    }


def read_beyondmimic(data: dict[str, np.ndarray], source: str = "motion") -> Motion:
    """A :class:`Motion` from ``beyondmimic`` arrays: the root from the first body's pose, the
    hinges from ``joint_pos`` (reordered by ``joint_names`` when given, else in our order)."""
    missing = [k for k in ("fps", "joint_pos", "body_pos_w", "body_quat_w") if k not in data]
    if missing:
        raise ValueError(f"{source}: a BeyondMimic motion needs fps, joint_pos, body_pos_w and body_quat_w; "
                         f"lacks {missing}")
    body_pos, body_quat = np.asarray(data["body_pos_w"]), np.asarray(data["body_quat_w"])
    if body_pos.ndim != 3 or body_quat.ndim != 3 or body_pos.shape[-1] != 3 or body_quat.shape[-1] != 4:
        raise ValueError(f"{source}: body_pos_w must be (T, B, 3) and body_quat_w (T, B, 4), got "
                         f"{body_pos.shape} and {body_quat.shape}")
    bodies = np.atleast_1d(data.get("body_names", BODY_NAMES))
    if str(bodies[0]) != BODY_NAMES[0]:
        raise ValueError(f"{source}: the first body must be the root {BODY_NAMES[0]!r}, got {bodies[0]!r}")
    fps = np.asarray(data["fps"]).reshape(-1)
    if fps.size != 1 or fps.dtype.kind not in "iuf":
        raise ValueError(f"{source}: fps must be one number, got {data['fps']!r}")
    names = tuple(str(n) for n in np.atleast_1d(data["joint_names"])) if "joint_names" in data else DOF_NAMES
    return Motion(fps=float(fps[0]), root_pos=body_pos[:, 0], root_quat=body_quat[:, 0],
                  dof_pos=np.asarray(data["joint_pos"]), dof_names=names).in_humanoid_order()


def write_motion_npz(motion: Motion, path: str | Path, layout: str = "fields", quat_order: str = "wxyz",
                     up_axis: str = "z") -> Path:
    """Write ``motion`` in ``layout`` (:data:`NPZ_LAYOUTS`) atomically.

    ``quat_order`` applies to the ``fields`` layout (``qpos`` and ``beyondmimic`` are always
    w x y z); ``up_axis`` to the ``smpl`` layout (``amass`` is always z up).
    """
    if layout == "fields":
        arrays = fields_layout(motion, quat_order)
    elif layout == "qpos":
        arrays = qpos_layout(motion)
    elif layout == "smpl":
        arrays = smpl_layout(motion, up_axis)
    elif layout == "amass":
        arrays = amass_layout(motion)
    elif layout == "beyondmimic":
        arrays = beyondmimic_layout(motion)
    else:
        raise ValueError(f"layout must be one of {NPZ_LAYOUTS}, got {layout!r}")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    return Path(path)


def read_motion_npz(path: str | Path) -> Motion:
    """A :class:`Motion` from a ``fields``, ``qpos`` or ``beyondmimic`` file of :func:`write_motion_npz`.

    SMPL and AMASS files are read by :func:`crisp_gym.smpl.load_smpl_params`.
    """
    path = Path(path)
    data = read_npz(path, "motion file")
    keys = set(data)
    if {"qpos", "qpos_names", "fps"} <= keys:
        names = [str(n) for n in data["qpos_names"]]
        qpos = data["qpos"]
        return Motion(fps=data["fps"], root_pos=qpos[:, :3], root_quat=qpos[:, 3:7], dof_pos=qpos[:, 7:],
                      dof_names=names[7:]).in_humanoid_order()
    if {"root_pos", "root_rot", "quat_order", "dof_pos", "dof_names", "fps"} <= keys:
        return Motion(fps=data["fps"], root_pos=data["root_pos"],
                      root_quat=from_order(data["root_rot"], str(data["quat_order"])),
                      dof_pos=data["dof_pos"], dof_names=data["dof_names"]).in_humanoid_order()
    if {"joint_pos", "body_pos_w", "body_quat_w"} <= keys:
        return read_beyondmimic(data, str(path))
    raise ValueError(f"{path} is neither a 'qpos' (qpos, qpos_names, fps), a 'fields' (root_pos, root_rot, "
                     f"quat_order, dof_pos, dof_names, fps) nor a 'beyondmimic' (fps, joint_pos, body_pos_w, "
                     f"body_quat_w) motion file; it has {sorted(keys)}")
