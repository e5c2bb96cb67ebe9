"""Reference motions of the humanoid: the :class:`Motion` type and the ``motion.npz`` format.

``motion.npz`` (``format_version`` 1) holds ``fps`` (scalar), ``root_pos`` (T, 3),
``root_quat`` (T, 4, w x y z), ``dof_pos`` (T, 69) named by ``dof_names`` (69,), and
``body_names`` (24,); optionally ``contacts`` (T, 24) bool and ``skeleton_offsets``
(24, 3). Files always carry their names, and :meth:`Motion.load` reorders hinges by name
into the humanoid's order, so no implied joint order is ever trusted.

Kinematics (body positions, orientations and velocities) come from MuJoCo itself
(:func:`compute_kinematics`), so the reference and the simulated humanoid can never disagree
on what a posture means.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import mujoco
import numpy as np
from scipy.ndimage import distance_transform_edt, gaussian_filter1d, maximum_filter1d, minimum_filter1d
from scipy.optimize import least_squares, minimize
from scipy.signal import butter, sosfiltfilt
from scipy.spatial.transform import Rotation, Slerp

from crisp_gym.atomic import atomic_path
from crisp_gym.file_errors import reading
from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, FEET, ROOT_JOINT, hinge_ranges
from crisp_gym.npz import read_npz

FORMAT_VERSION = 1
MIN_FPS = 1e-6
"""The lowest frame rate a :class:`Motion` may have at all (below it, filters' widths underflow);
importers bound frame rates far tighter, with messages that say why."""
_TRUNCATE = 2.0  # standard deviations the stance corrections' Gaussian low-pass reaches


def _low_pass(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass over frames, its kernel cut at ``_TRUNCATE`` standard deviations."""
    return gaussian_filter1d(x, sigma, mode="nearest", truncate=_TRUNCATE)


# Passes that lower the stance floor by its low-passed excess over the feet before the final
# envelope: on CMU 131_01-03 five halve the stance frames the envelope alone leaves floating.
_UNDERCUT_PASSES = 5
_STANCE_WINDOW = 0.5  # s each side: how far around a frame a planted foot's lowest height is sought
_STANCE_LIFT = 0.05  # m: a still foot this far above that height is in the air, not planted
_PLANT_HINGES = ("Hip_x", "Hip_y", "Knee_y")  # three hinges for the foot's three coordinates: no twist
PLANT_TOLERANCE = 2e-3  # m: a planted foot this close above its level stands on it (grounding's own error: < 1 mm)
_REACH_REGULARISATION = 1e-3  # m per rad: among postures that reach alike, the nearest the given
_RANGE_FIT_HINGES = ("Hip_x", "Hip_y", "Hip_z", "Knee_y")  # a leg put back after its joints were fitted into range


def _as_names(names, expected_len: int, what: str) -> tuple[str, ...]:
    names = tuple(str(n) for n in np.asarray(names).reshape(-1))
    if len(names) != expected_len:
        raise ValueError(f"{what} must name {expected_len} entries, got {len(names)}")
    return names


@dataclass(frozen=True)
class Motion:
    """A reference motion of the 24-body humanoid.

    Attributes:
        fps: frames per second of the arrays.
        root_pos: (T, 3) pelvis position in metres, world frame (z up).
        root_quat: (T, 4) pelvis orientation, w x y z.
        dof_pos: (T, 69) hinge angles in radians, in the order of ``dof_names``.
        dof_names: the 69 hinge names (:data:`crisp_gym.humanoid.DOF_NAMES` after loading).
        body_names: the 24 body names (:data:`crisp_gym.humanoid.BODY_NAMES`).
        contacts: optional (T, 24) bool, body in contact with the scene.
        skeleton_offsets: optional (24, 3) rest offsets of each joint from its parent (metres).
    """

    fps: float
    root_pos: np.ndarray
    root_quat: np.ndarray
    dof_pos: np.ndarray
    dof_names: tuple[str, ...] = DOF_NAMES
    body_names: tuple[str, ...] = BODY_NAMES
    contacts: np.ndarray | None = None
    skeleton_offsets: np.ndarray | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        fps = float(np.asarray(self.fps).reshape(()))
        if not (np.isfinite(fps) and fps >= MIN_FPS):
            raise ValueError(f"fps must be a finite frame rate of at least {MIN_FPS:g}, got {self.fps}")
        object.__setattr__(self, "fps", fps)
        arrays = {k: np.asarray(getattr(self, k), dtype=float) for k in ("root_pos", "root_quat", "dof_pos")}
        t = arrays["root_pos"].shape[0] if arrays["root_pos"].ndim == 2 else -1
        expected = {"root_pos": (t, 3), "root_quat": (t, 4), "dof_pos": (t, len(DOF_NAMES))}
        for key, shape in expected.items():
            if arrays[key].shape != shape:
                raise ValueError(f"{key} must have shape (T, {shape[1]}) with T frames shared by "
                                 f"root_pos/root_quat/dof_pos, got {arrays[key].shape}")
            bad = ~np.isfinite(arrays[key])
            if bad.any():
                frame = int(np.argwhere(bad)[0, 0])
                raise ValueError(f"{key} has non-finite values (first at frame {frame})")
        if t < 2:
            raise ValueError(f"a motion needs at least 2 frames, got {t}")
        norms = np.linalg.norm(arrays["root_quat"], axis=1)
        if np.any(np.abs(norms - 1.0) > 1e-3):
            frame = int(np.argmax(np.abs(norms - 1.0)))
            raise ValueError(f"root_quat must be unit quaternions (w, x, y, z); frame {frame} has "
                             f"norm {norms[frame]:.4f}")
        arrays["root_quat"] = arrays["root_quat"] / norms[:, None]
        for key, value in arrays.items():
            object.__setattr__(self, key, value)
        object.__setattr__(self, "dof_names", _as_names(self.dof_names, len(DOF_NAMES), "dof_names"))
        object.__setattr__(self, "body_names", _as_names(self.body_names, len(BODY_NAMES), "body_names"))
        if self.contacts is not None:
            contacts = np.asarray(self.contacts).astype(bool)
            if contacts.shape != (t, len(BODY_NAMES)):
                raise ValueError(f"contacts must have shape ({t}, 24), got {contacts.shape}")
            object.__setattr__(self, "contacts", contacts)
        if self.skeleton_offsets is not None:
            offsets = np.asarray(self.skeleton_offsets, dtype=float)
            if offsets.shape != (len(BODY_NAMES), 3):
                raise ValueError(f"skeleton_offsets must have shape (24, 3), got {offsets.shape}")
            object.__setattr__(self, "skeleton_offsets", offsets)

    @property
    def num_frames(self) -> int:
        return self.root_pos.shape[0]

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return (self.num_frames - 1) / self.fps

    def in_humanoid_order(self) -> Motion:
        """This motion with hinges and bodies reordered by name into the humanoid's order."""
        if self.dof_names == DOF_NAMES and self.body_names == BODY_NAMES:
            return self
        missing = sorted(set(DOF_NAMES) - set(self.dof_names))
        if missing:
            raise ValueError(f"dof_names lacks the humanoid's hinges {missing[:5]}...")
        missing_bodies = sorted(set(BODY_NAMES) - set(self.body_names))
        if missing_bodies:
            raise ValueError(f"body_names lacks the humanoid's bodies {missing_bodies[:5]}")
        dof_index = [self.dof_names.index(n) for n in DOF_NAMES]
        body_index = [self.body_names.index(n) for n in BODY_NAMES]
        return replace(
            self, dof_pos=self.dof_pos[:, dof_index], dof_names=DOF_NAMES, body_names=BODY_NAMES,
            contacts=None if self.contacts is None else self.contacts[:, body_index],
            skeleton_offsets=None if self.skeleton_offsets is None else self.skeleton_offsets[body_index])

    def qpos(self) -> np.ndarray:
        """(T, 76) MuJoCo qpos of the humanoid: root position, root quaternion, 69 hinges."""
        m = self.in_humanoid_order()
        return np.concatenate([m.root_pos, m.root_quat, m.dof_pos], axis=1)

    def qvel(self) -> np.ndarray:
        """(T, 75) MuJoCo qvel by central finite differences.

        The free joint's linear velocity is in the world frame and its angular velocity in the
        body frame, as MuJoCo defines them.
        """
        m = self.in_humanoid_order()
        dt = 1.0 / m.fps
        lin = np.gradient(m.root_pos, dt, axis=0)
        rot = Rotation.from_quat(m.root_quat, scalar_first=True)
        ang = local_angular_velocity(rot, dt)
        dof_vel = np.gradient(m.dof_pos, dt, axis=0)
        return np.concatenate([lin, ang, dof_vel], axis=1)

    def resample(self, fps: float) -> Motion:
        """The motion at ``fps``: slerp for the root orientation, linear for the rest.

        Hinge angles are joint coordinates (continuous, possibly beyond ±90°), so they are
        interpolated directly; converting them to rotations and back would alias.
        """
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        if abs(fps - self.fps) < 1e-9:
            return self
        t_old = np.arange(self.num_frames) / self.fps
        n_new = int(np.floor(self.duration * fps + 1e-9)) + 1
        if n_new < 2:
            raise ValueError(f"the motion lasts {self.duration:.3g} s ({self.num_frames} frames at {self.fps:g} fps), "
                             f"less than one frame at {fps:g} fps; a motion needs at least 2 frames")
        t_new = np.arange(n_new) / fps
        interp = lambda a: np.stack([np.interp(t_new, t_old, col) for col in a.T], axis=1)  # noqa: E731
        slerp = Slerp(t_old, Rotation.from_quat(self.root_quat, scalar_first=True))
        contacts = None
        if self.contacts is not None:
            nearest = np.clip(np.round(t_new * self.fps).astype(int), 0, self.num_frames - 1)
            contacts = self.contacts[nearest]
        return replace(self, fps=float(fps), root_pos=interp(self.root_pos),
                       root_quat=slerp(t_new).as_quat(scalar_first=True),
                       dof_pos=interp(self.dof_pos), contacts=contacts)

    def slice(self, start: int, stop: int | None = None) -> Motion:
        """Frames ``start:stop``."""
        sl = slice(start, stop)
        return replace(self, root_pos=self.root_pos[sl], root_quat=self.root_quat[sl],
                       dof_pos=self.dof_pos[sl],
                       contacts=None if self.contacts is None else self.contacts[sl])

    def translated(self, offset) -> Motion:
        """The motion moved by a constant world offset (3,)."""
        return replace(self, root_pos=self.root_pos + np.asarray(offset, dtype=float))

    def save(self, path: str | Path) -> Path:
        """Write ``motion.npz`` atomically (temp file, then rename)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = dict(
            format_version=np.int64(FORMAT_VERSION), fps=np.float64(self.fps),
            root_pos=self.root_pos, root_quat=self.root_quat, dof_pos=self.dof_pos,
            dof_names=np.array(self.dof_names), body_names=np.array(self.body_names))
        if self.contacts is not None:
            arrays["contacts"] = self.contacts
        if self.skeleton_offsets is not None:
            arrays["skeleton_offsets"] = self.skeleton_offsets
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Motion:
        """Read and validate a ``motion.npz``; hinges are returned in the humanoid's order."""
        path = Path(path)
        data = read_npz(path, "motion file (motion.npz)")
        with reading(path, "motion.npz"):
            return cls._from_arrays(data, path)

    @classmethod
    def _from_arrays(cls, data: dict[str, np.ndarray], path: Path) -> Motion:
        required = {"fps", "root_pos", "root_quat", "dof_pos", "dof_names", "body_names"}
        if not required <= data.keys():
            raise ValueError(f"{path} is not a motion.npz: missing {sorted(required - data.keys())} "
                             f"(has {sorted(data)})")
        version = np.asarray(data.get("format_version", FORMAT_VERSION))
        if version.size != 1 or version.dtype.kind not in "iuf" or int(version.reshape(())) != FORMAT_VERSION:
            raise ValueError(f"{path}: format_version {version} is not supported (expected {FORMAT_VERSION})")
        try:
            motion = cls(
                fps=data["fps"], root_pos=data["root_pos"], root_quat=data["root_quat"],
                dof_pos=data["dof_pos"], dof_names=data["dof_names"], body_names=data["body_names"],
                contacts=data.get("contacts"), skeleton_offsets=data.get("skeleton_offsets"))
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None
        return motion.in_humanoid_order()


MAX_ROOT_DISTANCE = 1e4
"""m: a root farther than this from the origin is a unit or parsing error, not a capture."""
MAX_ROOT_SPEED = 30.0
"""m/s: 2.5x a sprinter's top speed."""
MAX_HINGE_SPEED = 300.0
"""rad/s: 17,000 deg/s; raw captured wrists flicker at up to 113 rad/s (CMU 131_01)."""
MAX_HINGE_ANGLE = 1e3
"""rad: hinge tracks are unwrapped for continuity (a turning knee of a video estimate reaches 4π),
so only a corrupt value lies beyond this."""


def check_plausible(motion: Motion) -> Motion:
    """``motion`` if a body could do it, else ValueError naming the first frame and joint that
    no body can reach: a root beyond :data:`MAX_ROOT_DISTANCE`, moving faster than
    :data:`MAX_ROOT_SPEED`, a hinge beyond :data:`MAX_HINGE_ANGLE` or turning faster than
    :data:`MAX_HINGE_SPEED`."""
    m = motion.in_humanoid_order()
    distance = np.abs(m.root_pos).max(axis=1)  # not a norm: squaring 1e300 overflows
    if distance.max() > MAX_ROOT_DISTANCE:
        k = int(np.argmax(distance > MAX_ROOT_DISTANCE))
        raise ValueError(f"frame {k}: the root is {distance[k]:.3g} m from the origin "
                         f"(at most {MAX_ROOT_DISTANCE:g}): wrong units or a corrupt file?")
    speed = np.linalg.norm(np.diff(m.root_pos, axis=0), axis=1) * m.fps
    if speed.max() > MAX_ROOT_SPEED:
        k = int(np.argmax(speed))
        raise ValueError(f"frame {k}: the root moves at {speed[k]:.3g} m/s (at most {MAX_ROOT_SPEED:g}): "
                         f"wrong units, frame rate or a jump in the file?")
    checks = (("angle", np.abs(m.dof_pos), MAX_HINGE_ANGLE, "rad"),
              ("speed", np.abs(np.diff(m.dof_pos, axis=0)) * m.fps, MAX_HINGE_SPEED, "rad/s"))
    for what, values, limit, unit in checks:
        if values.max() > limit:
            k, j = np.unravel_index(int(np.argmax(values)), values.shape)
            raise ValueError(f"frame {k}: hinge {DOF_NAMES[j]} {what} {values[k, j]:.3g} {unit} (at most {limit:.3g})")
    return motion


def local_angular_velocity(rotations: Rotation, dt: float) -> np.ndarray:
    """(T, 3) body-frame angular velocity of a rotation sequence, by central differences."""
    n = len(rotations)
    prev = np.r_[0, np.arange(n - 1)]
    nxt = np.r_[np.arange(1, n), n - 1]
    span = (nxt - prev) * dt
    return (rotations[prev].inv() * rotations[nxt]).as_rotvec() / span[:, None]


_MAX_BRANCH_STEP = np.deg2rad(45.0)  # how much farther than the nearest triple the in-range one may be


def rotations_to_hinge_angles(rotations: np.ndarray, ranges: np.ndarray | None = None) -> np.ndarray:
    """(T, J, 3) continuous x-y-z hinge angles for (T, J, 3, 3) local rotation matrices.

    Every rotation has two intrinsic XYZ Euler triples, ``(a, b, c)`` and
    ``(a + π, π - b, c + π)``; the first frame takes the one nearer the rest pose, and each
    later frame the one (with 2π unwrapping) nearest the previous frame. This keeps a knee
    flexed past 90° a knee flexion rather than a flipped twist. With ``ranges`` ((J, 3, 2)
    radians), a triple's distance outside them counts ten times its distance from the previous
    frame, as long as it is at most 45° farther than the nearest: crossing ``b = ±90°`` (a hip
    flexed to the horizontal) the two triples come close, and continuity alone can follow the
    one the joint cannot reach.
    """
    rotations = np.asarray(rotations, dtype=float)
    t, j = rotations.shape[:2]
    first = Rotation.from_matrix(rotations.reshape(-1, 3, 3)).as_euler("XYZ").reshape(t, j, 3)
    second = first + np.array([np.pi, 0.0, np.pi])
    second[..., 1] = np.pi - first[..., 1]
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    first, second = wrap(first), wrap(second)

    def outside(angles: np.ndarray) -> np.ndarray:
        if ranges is None:
            return np.zeros(j)
        excess = np.maximum(ranges[..., 0] - angles, 0.0) + np.maximum(angles - ranges[..., 1], 0.0)
        return 10.0 * excess.sum(axis=-1)

    out = np.empty_like(first)
    previous = np.zeros((j, 3))
    for k in range(t):
        if k == 0:  # nearest the rest pose, without unwrapping
            candidates = [first[0], second[0]]
        else:
            candidates = [previous + wrap(option - previous) for option in (first[k], second[k])]
        dist = [np.linalg.norm(c - previous, axis=1) for c in candidates]
        # Never jump to reach the range: a step that large would whip the simulated joint round.
        near = [d <= np.minimum(*dist) + _MAX_BRANCH_STEP for d in dist]
        cost = [np.where(n, d + outside(c), np.inf) for n, d, c in zip(near, dist, candidates)]
        out[k] = np.where((cost[0] <= cost[1])[:, None], candidates[0], candidates[1])
        previous = out[k]
    return out


def fit_hinges_into_range(angles: np.ndarray, ranges: np.ndarray, continuity: float = 1e-3) -> np.ndarray:
    """(T, J, 3) hinge angles inside ``ranges`` ((J, 3, 2) radians) whose rotations are nearest
    those of ``angles``: the joint's orientation is kept as well as its range allows.

    Clipping each hinge on its own does not do that near ``b = ±90°`` (a hip flexed to the
    horizontal), where only ``a ± c`` sets the rotation: a triple with ``a`` and ``c`` both far
    outside can be the same rotation as one well inside, and clipping both can turn the joint by
    90° or more. Each out-of-range joint is fitted by bounded least
    squares on the rotation matrices' difference, from its clipped angles and from the previous
    frame's answer; ``continuity`` weighs the squared distance from the previous frame, so that
    among equally good fits the motion stays smooth.
    """
    angles = np.asarray(angles, dtype=float)
    low, high = ranges[..., 0], ranges[..., 1]
    fitted = np.clip(angles, low, high)
    targets = hinge_angles_to_rotations(angles)
    for k, j in zip(*np.nonzero(np.any(fitted != angles, axis=-1))):
        previous = fitted[k - 1, j] if k > 0 else fitted[k, j]
        cost = _RotationDistance(targets[k, j], previous, continuity)
        starts = (fitted[k, j], previous)
        fits = [minimize(cost, s, jac=True, method="L-BFGS-B", bounds=list(zip(low[j], high[j]))) for s in starts]
        fitted[k, j] = min(fits, key=lambda f: f.fun).x
    return fitted


@dataclass(frozen=True)
class _RotationDistance:
    """``||R(x) - target||² + continuity ||x - previous||²`` and its gradient, for x-y-z hinge
    angles ``x`` (``R = Rx(a) Ry(b) Rz(c)``, as :func:`hinge_angles_to_rotations`): written out,
    because finite differences through ``Rotation`` made the fit most of an import's time."""

    target: np.ndarray
    previous: np.ndarray
    continuity: float

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        (ca, cb, cc), (sa, sb, sc) = np.cos(x), np.sin(x)
        rx = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
        ry = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
        rz = np.array([[cc, -sc, 0.0], [sc, cc, 0.0], [0.0, 0.0, 1.0]])
        drx = np.array([[0.0, 0.0, 0.0], [0.0, -sa, -ca], [0.0, ca, -sa]])
        dry = np.array([[-sb, 0.0, cb], [0.0, 0.0, 0.0], [-cb, 0.0, -sb]])
        drz = np.array([[-sc, -cc, 0.0], [cc, -sc, 0.0], [0.0, 0.0, 0.0]])
        residual = rx @ ry @ rz - self.target
        step = x - self.previous
        partials = (drx @ ry @ rz, rx @ dry @ rz, rx @ ry @ drz)
        gradient = np.array([2.0 * np.sum(residual * d) for d in partials]) + 2.0 * self.continuity * step
        return float(np.sum(residual**2) + self.continuity * np.sum(step**2)), gradient


def hinge_angles_to_rotations(angles: np.ndarray) -> np.ndarray:
    """(..., 3, 3) local rotations for (..., 3) x-y-z hinge angles (inverse of the above)."""
    angles = np.asarray(angles, dtype=float)
    mats = Rotation.from_euler("XYZ", angles.reshape(-1, 3)).as_matrix()
    return mats.reshape(*angles.shape[:-1], 3, 3)


@dataclass(frozen=True)
class MotionKinematics:
    """Per-frame quantities of a motion on a model, all in the world frame.

    Attributes:
        qpos: (T, nq), qvel: (T, nv) of the humanoid.
        body_pos: (T, 24, 3) body (joint) positions; body_quat: (T, 24, 4) w x y z.
        body_lin_vel: (T, 24, 3); body_ang_vel: (T, 24, 3), world frame.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    body_pos: np.ndarray
    body_quat: np.ndarray
    body_lin_vel: np.ndarray
    body_ang_vel: np.ndarray


def humanoid_body_ids(model: mujoco.MjModel) -> np.ndarray:
    """Ids of the 24 humanoid bodies in :data:`BODY_NAMES` order (also inside a scene model)."""
    try:
        return np.array([model.body(name).id for name in BODY_NAMES])
    except KeyError as err:
        raise ValueError(f"the model lacks a humanoid body: {err}") from None


def humanoid_qpos_adr(model: mujoco.MjModel) -> int:
    """Start of the humanoid's qpos block in ``model`` (its free joint)."""
    return int(model.jnt_qposadr[model.joint(ROOT_JOINT).id])


def compute_kinematics(motion: Motion, model: mujoco.MjModel) -> MotionKinematics:
    """Forward kinematics of ``motion`` with MuJoCo, and velocities by central differences."""
    motion = motion.in_humanoid_order()
    data = mujoco.MjData(model)
    ids = humanoid_body_ids(model)
    adr = humanoid_qpos_adr(model)
    qpos = motion.qpos()
    t = motion.num_frames
    body_pos = np.empty((t, len(ids), 3))
    body_quat = np.empty((t, len(ids), 4))
    for k in range(t):
        data.qpos[adr:adr + qpos.shape[1]] = qpos[k]
        mujoco.mj_kinematics(model, data)
        body_pos[k] = data.xpos[ids]
        body_quat[k] = data.xquat[ids]
    dt = 1.0 / motion.fps
    rot = Rotation.from_quat(body_quat.reshape(-1, 4), scalar_first=True)
    local = local_angular_velocity_batched(body_quat, dt)
    ang_world = rot.apply(local.reshape(-1, 3)).reshape(t, len(ids), 3)
    return MotionKinematics(
        qpos=qpos, qvel=motion.qvel(), body_pos=body_pos, body_quat=body_quat,
        body_lin_vel=np.gradient(body_pos, dt, axis=0), body_ang_vel=ang_world)


def local_angular_velocity_batched(quats: np.ndarray, dt: float) -> np.ndarray:
    """(T, B, 3) body-frame angular velocities of (T, B, 4) quaternion tracks."""
    t, b = quats.shape[:2]
    out = np.empty((t, b, 3))
    for i in range(b):
        out[:, i] = local_angular_velocity(Rotation.from_quat(quats[:, i], scalar_first=True), dt)
    return out


def foot_sole_heights(motion: Motion, model: mujoco.MjModel) -> np.ndarray:
    """(T,) height of the lowest point of the foot geoms in each frame."""
    return side_sole_heights(motion, model).min(axis=1)


def side_sole_heights(motion: Motion, model: mujoco.MjModel) -> np.ndarray:
    """(T, 2) height of the lowest point of the left / right foot's geoms (ankle and toe) in each frame."""
    motion = motion.in_humanoid_order()
    data = mujoco.MjData(model)
    adr = humanoid_qpos_adr(model)
    sides = ({model.body(name).id for name in FEET[:2]}, {model.body(name).id for name in FEET[2:]})
    geoms = [[g for g in range(model.ngeom) if model.geom_bodyid[g] in side] for side in sides]
    qpos = motion.qpos()
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    lowest = np.empty((motion.num_frames, 2))
    for k in range(motion.num_frames):
        data.qpos[adr:adr + qpos.shape[1]] = qpos[k]
        mujoco.mj_kinematics(model, data)
        for i, side in enumerate(geoms):
            lowest[k, i] = min((data.geom_xpos[g] + (corners * model.geom_size[g])
                                @ data.geom_xmat[g].reshape(3, 3).T)[:, 2].min() for g in side)
    return lowest


def ground(motion: Motion, model: mujoco.MjModel, floor_height: float = 0.0,
           percentile: float = 5.0) -> Motion:
    """Shift the motion vertically so its lowest foot rests on ``floor_height``.

    The lowest foot point per frame is taken at a low ``percentile`` over the clip rather than
    the minimum, so a few noisy frames cannot sink the whole motion.
    """
    sole = foot_sole_heights(motion, model)
    return motion.translated([0.0, 0.0, floor_height - np.percentile(sole, percentile)])


@dataclass(frozen=True)
class StanceGrounding:
    """Settings of :func:`stance_floor`, which follows a capture whose floor height drifts, and
    of :func:`level_feet`, which lays the planted feet flat.

    Attributes:
        stance_speed: m/s. A foot is planted while its ankle and toe joints both move
            slower than this (velocity-threshold contact detection, as gait analysis detects
            foot contacts; a planted foot's joints barely move), within 5 cm of their lowest
            height of the surrounding second (a jumping foot also stands still, at the top of
            its flight).
        smoothing: s. Standard deviation of the Gaussian low-pass applied to the floor
            estimate (half power at about 0.13 / smoothing Hz), so the correction follows drift
            over steps and postures without adding jitter from frame-to-frame foot noise.
        max_shift: m. The floor estimate stays within this distance of its midpoint, so the
            root path stays within it of the source's up to one constant floor offset. It
            bounds what a misdetected stance (a foot held still in the air) can flatten, and
            must cover a capture's own floor error: the planted feet of CMU 131_01 sit 13 cm
            lower in its crouch than in its final stand (the file's own ankle and toe joints
            do), 8-10 cm in 131_02.
        plant: bend the legs so that a planted foot standing above the floor comes down onto it
            (:func:`plant_feet`): each frame is grounded on its lower foot, and a capture's other
            planted foot, its body's legs not ours, often stands 1-2 cm above the floor. Off by
            default: a reference planted this way was no easier to track (a video motion learned
            more slowly with it in two of three seeds; ``docs/motion_import.md``).
        plant_blend: s. Over this time before and after a stance the planting correction fades
            out, so a foot lands and lifts off without a jump.
    """

    stance_speed: float = 0.2
    smoothing: float = 0.05
    max_shift: float = 0.08
    plant: bool = False
    plant_blend: float = 0.1

    def __post_init__(self) -> None:
        for name in ("stance_speed", "smoothing", "max_shift", "plant_blend"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"StanceGrounding.{name} must be a positive number, got {value}")


def planted_feet(motion: Motion, model: mujoco.MjModel, stance_speed: float = 0.2) -> np.ndarray:
    """(T, 2) bool: whether the left / right foot is planted (see :class:`StanceGrounding`)."""
    kin = compute_kinematics(motion, model)
    ids = [BODY_NAMES.index(name) for name in FEET]
    speed = np.linalg.norm(kin.body_lin_vel[:, ids], axis=-1)  # (T, 4): L ankle, L toe, R ankle, R toe
    still = np.stack([speed[:, :2].max(axis=1), speed[:, 2:].max(axis=1)], axis=1) < stance_speed
    # A foot also stands still at the top of a jump: a planted one is near its lowest height
    # of the surrounding second.
    height = kin.body_pos[:, ids, 2]
    low = np.stack([height[:, :2].min(axis=1), height[:, 2:].min(axis=1)], axis=1)
    window = 2 * int(round(_STANCE_WINDOW * motion.fps)) + 1
    return still & (low - minimum_filter1d(low, window, axis=0, mode="nearest") < _STANCE_LIFT)


def stance_floor(motion: Motion, model: mujoco.MjModel, config: StanceGrounding = StanceGrounding()) -> np.ndarray:
    """(T,) height of the floor under the motion in each frame, estimated from its planted feet.

    In a frame with a planted foot the floor is at the lowest foot point (a lower, sliding foot
    touches the floor too); between such frames it is interpolated, and lowered wherever a foot
    would pass below it. The estimate is clamped to ``max_shift`` around the midpoint of the
    planted frames' heights (balancing floating against sinking where the source's feet vary
    more than that), then low-passed, and never rises above that clamped estimate: where the
    low-pass would cut through a short dip of the feet, it is lowered by its low-passed excess
    (a few passes) and then by a smooth envelope of what is left, so no foot sinks into the
    floor within the clamp. Without any planted frame the floor is constant, at the 5th
    percentile of the lowest foot point (as :func:`ground`).
    """
    sole = foot_sole_heights(motion, model)
    planted = planted_feet(motion, model, config.stance_speed).any(axis=1)
    if not planted.any():
        return np.full(motion.num_frames, np.percentile(sole, 5.0))
    frames = np.arange(motion.num_frames)
    floor = np.minimum(np.interp(frames, frames[planted], sole[planted]), sole)
    mid = (sole[planted].min() + sole[planted].max()) / 2
    floor = np.clip(floor, mid - config.max_shift, mid + config.max_shift)
    sigma = config.smoothing * motion.fps
    smooth = _low_pass(floor, sigma)
    for _ in range(_UNDERCUT_PASSES):  # pull the curve under short dips, spreading them little
        smooth -= _low_pass(np.maximum(smooth - floor, 0.0), sigma)
    # Each frame's remaining excess is inside the reach of its neighbours' maxima, so the
    # low-passed maxima (weights summing to one) are at least that excess: the result stays at or
    # below ``floor``.
    reach = int(_TRUNCATE * sigma + 0.5)  # the kernel's radius in frames, as scipy rounds it
    excess = maximum_filter1d(np.maximum(smooth - floor, 0.0), 2 * reach + 1, mode="nearest")
    return np.clip(smooth - _low_pass(excess, sigma), mid - config.max_shift, mid + config.max_shift)


def ground_stance(motion: Motion, model: mujoco.MjModel, config: StanceGrounding = StanceGrounding(),
                  floor_height: float = 0.0) -> Motion:
    """Shift each frame vertically so the planted feet rest on ``floor_height`` (see :func:`stance_floor`).

    Unlike :func:`ground`'s single offset, this follows a capture whose floor drifts, by a
    low-passed correction that never departs more than ``config.max_shift`` from a constant.
    """
    floor = stance_floor(motion, model, config)
    offset = np.zeros((motion.num_frames, 3))
    offset[:, 2] = floor_height - floor
    grounded = replace(motion, root_pos=motion.root_pos + offset)
    return plant_feet(grounded, model, config, floor_height) if config.plant else grounded


def plant_feet(motion: Motion, model: mujoco.MjModel, config: StanceGrounding = StanceGrounding(),
               floor_height: float = 0.0) -> Motion:
    """The motion with each planted foot that stands above the floor lowered onto it: its leg bent
    at the hip and knee (flexion and abduction: no twist), the ankle turned back so that the foot
    keeps its orientation and moves straight down.

    Each stance (a run of planted frames) is lowered as a whole, by as much as its lowest frame
    hovers above the floor, or above the other foot's level where that one stands higher too (a
    frame grounded within ``max_shift`` of a drifting floor): a heel rising before toe-off keeps
    its rise. Around a stance the correction fades out over ``config.plant_blend`` seconds. Nothing
    is raised, no foot is taken below the floor and the pelvis does not move. A leg that cannot
    reach (straight already) comes as close as its joint ranges let it.
    """
    motion = motion.in_humanoid_order()
    planted = planted_feet(motion, model, config.stance_speed)
    sole = side_sole_heights(motion, model)
    frames = np.arange(motion.num_frames)
    drop = np.zeros((motion.num_frames, 2))  # per stance, how far each foot comes down (<= 0)
    for i, on in enumerate(planted.T):
        if not on.any():
            continue
        # as low as the floor, not below the other foot where that one stands too
        level = np.where(planted[:, 1 - i], np.maximum(floor_height, sole[:, 1 - i]), floor_height)
        # One drop per stance, by its lowest hover: a heel rising before toe-off keeps its rise.
        for run in np.split(frames[on], np.flatnonzero(np.diff(frames[on]) > 1) + 1):
            drop[run, i] = min(np.min(level[run] + PLANT_TOLERANCE - sole[run, i]), 0.0)
    return lower_feet(motion, model, planted, drop, config.plant_blend, floor_height, sole)


def fit_into_range(motion: Motion, model: mujoco.MjModel) -> Motion:
    """``motion`` with every joint inside the humanoid's ranges and the feet where they were.

    Each joint is first given the in-range orientation nearest its own
    (:func:`fit_hinges_into_range`). A leg changed that way then has its ankle put back where it
    was and its foot turned back, by the leg solve of :func:`plant_feet` (here on the hip's three
    hinges and the knee's flexion, then the ankle) as far as the ranges allow: a hip turned into
    range swings the whole leg, and a foot on the floor that swings with it slides. In CMU
    131_01's side lunge the right hip's hinges lie up to 77° outside their ranges while the
    captured foot stands still; clipped, the hip turned by up to 19° and that foot slid 32 cm in
    half a second. The pelvis does not move.
    """
    motion = motion.in_humanoid_order()
    t = motion.num_frames
    angles = motion.dof_pos.reshape(t, -1, 3)
    fitted = fit_hinges_into_range(angles, hinge_ranges().reshape(-1, 3, 2))
    changed = np.any(fitted != angles, axis=-1)  # (T, 23): joints that had to move
    if not changed.any():
        return motion
    before = compute_kinematics(motion, model)
    qpos = replace(motion, dof_pos=fitted.reshape(t, -1)).qpos()
    leg = _LegSolver(model)
    for side in "LR":
        ankle = BODY_NAMES.index(f"{side}_Ankle")
        leg_joints = [BODY_NAMES.index(f"{side}_{b}") - 1 for b in ("Hip", "Knee", "Ankle")]
        for k in np.flatnonzero(changed[:, leg_joints].any(axis=1)):
            orientation = Rotation.from_quat(before.body_quat[k, ankle], scalar_first=True).as_matrix()
            leg.reach(qpos[k], side, before.body_pos[k, ankle], orientation, _RANGE_FIT_HINGES)
    return replace(motion, dof_pos=qpos[:, 7:])


def range_fit_change(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """What :func:`fit_into_range` did, from the (T, 69) hinge angles before and after: the share
    of hinge values it changed and the largest turn of a joint, in degrees."""
    t = len(before)
    before, after = np.reshape(before, (t, -1, 3)), np.reshape(after, (t, -1, 3))
    changed = np.abs(after - before) > 1e-9
    if not changed.any():
        return 0.0, 0.0
    turn = Rotation.from_matrix(hinge_angles_to_rotations(after).reshape(-1, 3, 3)).inv() * \
        Rotation.from_matrix(hinge_angles_to_rotations(before).reshape(-1, 3, 3))
    return float(np.mean(changed)), float(np.rad2deg(turn.magnitude().max()))


def lower_feet(motion: Motion, model: mujoco.MjModel, on: np.ndarray, drop: np.ndarray, blend: float,
               floor_height: float = 0.0, sole: np.ndarray | None = None) -> Motion:
    """The motion with foot ``i`` (0 left, 1 right) lowered by ``drop[k, i]`` m (<= 0) in the frames
    where ``on[k, i]``, by bending its leg as :func:`plant_feet` does; ``drop`` elsewhere is ignored.

    Around those frames the drop fades out linearly over ``blend`` seconds (interpolated between
    them), so a foot lands and lifts off without a jump. No foot is taken below ``floor_height``
    and the pelvis does not move. ``sole``: the (T, 2) :func:`side_sole_heights`, if already known.
    """
    motion = motion.in_humanoid_order()
    sole = side_sole_heights(motion, model) if sole is None else sole
    frames = np.arange(motion.num_frames)
    blend_frames = max(blend * motion.fps, 1.0)
    faded = np.zeros((motion.num_frames, 2))
    for i, foot_on in enumerate(np.asarray(on, dtype=bool).T):
        if not foot_on.any():
            continue
        weight = np.clip(1.0 - distance_transform_edt(~foot_on) / blend_frames, 0.0, 1.0)
        faded[:, i] = np.maximum(weight * np.interp(frames, frames[foot_on], drop[foot_on, i]), floor_height - sole[:, i])
    faded = np.minimum(faded, 0.0)
    if not np.any(faded < 0.0):
        return motion
    leg = _LegSolver(model)
    qpos = motion.qpos()  # a fresh array: the rows are changed in place
    for k, i in zip(*np.nonzero(faded < 0.0)):
        leg.lower(qpos[k], "LR"[i], faded[k, i])
    return replace(motion, dof_pos=qpos[:, 7:])


class _LegSolver:
    """Moves one foot of a posture: bounded least squares on some of its leg's hinges to put the
    ankle at a target, then the ankle turned to a given orientation."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model, self.data = model, mujoco.MjData(model)
        self.adr = humanoid_qpos_adr(model)
        self.ranges = hinge_ranges()
        self.ankle_hinges = {s: np.array([DOF_NAMES.index(f"{s}_Ankle_{axis}") for axis in "xyz"]) for s in "LR"}

    def lower(self, qpos: np.ndarray, side: str, drop: float) -> None:
        """Lower the ``side`` foot of ``qpos`` (the motion's row: root then hinges) by ``drop`` m,
        in place, bending the hip and knee without twist and keeping the foot's orientation."""
        ankle = self.model.body(f"{side}_Ankle").id
        self._pose(qpos)
        self.reach(qpos, side, self.data.xpos[ankle] + [0.0, 0.0, drop], self.data.xmat[ankle].reshape(3, 3).copy(),
                   _PLANT_HINGES)

    def reach(self, qpos: np.ndarray, side: str, target: np.ndarray, orientation: np.ndarray,
              hinges: tuple[str, ...]) -> None:
        """Move the ``side`` ankle of ``qpos`` to ``target`` (world, m) with its leg's ``hinges``
        (e.g. ``"Hip_x"``), then turn the foot to ``orientation`` (world 3x3), as far as the joint
        ranges allow, in place. Among equally close postures the one nearest the given is taken."""
        m, d = self.model, self.data
        columns = 7 + np.array([DOF_NAMES.index(f"{side}_{name}") for name in hinges])
        ankle_hinges = self.ankle_hinges[side]
        ankle, knee = m.body(f"{side}_Ankle").id, m.body(f"{side}_Knee").id
        # the joint ranges, widened to hold the posture's own angles (a retarget that was not clipped)
        lo, hi = np.minimum(self.ranges[:, 0], qpos[7:]), np.maximum(self.ranges[:, 1], qpos[7:])
        start = qpos[columns].copy()

        def residual(x: np.ndarray) -> np.ndarray:
            qpos[columns] = x
            self._pose(qpos)
            return np.concatenate([d.xpos[ankle] - target, _REACH_REGULARISATION * (x - start)])

        fit = least_squares(residual, start, bounds=(lo[columns - 7], hi[columns - 7]), xtol=1e-10)
        qpos[columns] = fit.x
        self._pose(qpos)
        local = d.xmat[knee].reshape(3, 3).T @ orientation  # the ankle's rotation in the shin's frame
        angles = rotations_to_hinge_angles(local[None, None], self.ranges[ankle_hinges][None])[0, 0]
        qpos[7 + ankle_hinges] = np.clip(angles, lo[ankle_hinges], hi[ankle_hinges])

    def _pose(self, qpos: np.ndarray) -> None:
        self.data.qpos[self.adr:self.adr + len(qpos)] = qpos
        mujoco.mj_kinematics(self.model, self.data)


def low_pass_joints(motion: Motion, cutoff_hz: float, bodies: tuple[str, ...] | None = None) -> Motion:
    """``motion`` with the hinge angles of ``bodies`` (all when ``None``) low-passed (zero-phase
    4th-order Butterworth, the usual treatment of captured joint angles; walking has no content
    above ~6 Hz).

    Captured hands flicker: CMU's wrist markers turn the wrist by up to 6,500 °/s relative to the
    forearm, which a servo cannot follow and a policy sees as a velocity far outside anything it
    was trained on. The root is left as it is; clips too short to filter are returned unchanged.
    """
    if not (np.isfinite(cutoff_hz) and cutoff_hz > 0):
        raise ValueError(f"cutoff_hz must be a positive frequency, got {cutoff_hz}")
    nyquist = motion.fps / 2
    if cutoff_hz >= nyquist:
        return motion
    sos = butter(4, cutoff_hz / nyquist, output="sos")
    if motion.num_frames <= 3 * (2 * len(sos) + 1):  # sosfiltfilt's default padding
        return motion
    columns = [i for i, name in enumerate(DOF_NAMES) if bodies is None or name.rsplit("_", 1)[0] in bodies]
    motion = motion.in_humanoid_order()
    dof = motion.dof_pos.copy()
    dof[:, columns] = sosfiltfilt(sos, dof[:, columns], axis=0)
    return replace(motion, dof_pos=dof)


def level_feet(motion: Motion, model: mujoco.MjModel, config: StanceGrounding = StanceGrounding()) -> Motion:
    """The motion with each planted foot flat on a level floor: its sole not rolled, its toes level.

    A foot planted on a flat floor has a level sole and its toes on the floor. Motion capture
    often breaks both: a skeleton whose rest legs stand apart rolls the sole of a straight leg
    by about that angle (CMU's by 10-20°), and toes, tracked by one marker if at all, curl
    40° into the floor or flip by 80° within a few frames. Grounding then stands the body on a
    foot edge or on curled toe tips, centimetres above a flat stance, and the simulated toe's
    stiff servo fights the floor at its torque limit.

    The roll (the foot turned about its length) is measured in the foot's planted frames (see
    :class:`StanceGrounding`), interpolated between them, low-passed and turned out of every
    frame; without a planted frame it is kept. The toes are posed from the floor alone: level
    while the toe joint stands still (from heel strike to toe-off, bent up as the heel lifts),
    and in the air unbending steadily from their bend at toe-off to their bend at the next
    touchdown (a foot pitching 80° in the air does not whip them round: the light toe's servo
    saturates above 7.5 rad/s); straight if the toe joint never stands still. Positions of every
    joint but the toes are unchanged.
    """
    motion = motion.in_humanoid_order()
    planted = planted_feet(motion, model, config.stance_speed)
    kin = compute_kinematics(motion, model)
    foot_axes = Rotation.from_quat(kin.body_quat.reshape(-1, 4), scalar_first=True)
    foot_axes = foot_axes.as_matrix().reshape(motion.num_frames, len(BODY_NAMES), 3, 3)
    sigma = config.smoothing * motion.fps
    frames = np.arange(motion.num_frames)
    dof = motion.dof_pos.reshape(motion.num_frames, -1, 3).copy()  # (T, 23, 3): non-root bodies
    for side, on in zip("LR", planted.T):
        ankle, toe = BODY_NAMES.index(f"{side}_Ankle"), BODY_NAMES.index(f"{side}_Toe")
        axes = foot_axes[:, ankle]  # columns: the foot's length, its left, its sole normal
        roll = np.arctan2(axes[:, 2, 1], axes[:, 2, 2])
        roll = _low_pass(np.interp(frames, frames[on], roll[on]), sigma) if on.any() else np.zeros(motion.num_frames)
        unroll = Rotation.from_rotvec(-roll[:, None] * [1.0, 0.0, 0.0]).as_matrix()
        local = hinge_angles_to_rotations(dof[:, ankle - 1]) @ unroll
        dof[:, ankle - 1] = rotations_to_hinge_angles(local[:, None])[:, 0]
        axes = axes @ unroll
        level = np.arctan2(axes[:, 2, 0], axes[:, 2, 2])  # toe flexion that makes the toes level
        # The toes stay down from heel strike to toe-off, while the ankle already moves on.
        toes_down = np.linalg.norm(kin.body_lin_vel[:, toe, :2], axis=1) < config.stance_speed
        dof[:, toe - 1] = 0.0
        if toes_down.any():  # in the air the bend goes steadily from toe-off to the next touchdown
            dof[:, toe - 1, 1] = np.interp(frames, frames[toes_down], level[toes_down])
    return replace(motion, dof_pos=dof.reshape(motion.num_frames, -1))
