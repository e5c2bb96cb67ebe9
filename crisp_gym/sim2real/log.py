"""The real-log format of the sim-to-real gap tool, and its validation against a model.

A log is what a user recorded on the real system: ``time`` (T,), ``qpos`` (T, n) of the
scalar (hinge/slide) joints named by ``joint_names`` (n,), ``ctrl`` (T, m) named by
``actuator_names`` (m,), optionally ``qvel`` (T, n), and optionally ``ctrl_enabled``
(T, m) bool (``False`` where an actuator was switched off, e.g. a servo with torque
disabled: it then exerts no force at all). Commands are sample-and-hold between
samples. Validation happens once, at the boundary, so the replay can trust the arrays
and users get an error that names the problem rather than a NaN deep in a fit.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import mujoco
import numpy as np

from crisp_gym.atomic import atomic_path
from crisp_gym.npz import read_npz

FORMAT_VERSION = 1
_SCALAR_JOINTS = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


@dataclass(frozen=True)
class RealLog:
    """One recorded trajectory (see the module docstring for the fields' meaning).

    ``meta`` holds provenance (source file, gains, trajectory name); it is written to the
    npz as JSON and never drives the replay.
    """

    time: np.ndarray
    qpos: np.ndarray
    ctrl: np.ndarray
    joint_names: tuple[str, ...]
    actuator_names: tuple[str, ...]
    qvel: np.ndarray | None = None
    ctrl_enabled: np.ndarray | None = None
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        time = np.asarray(self.time, dtype=float).reshape(-1)
        qpos = np.asarray(self.qpos, dtype=float)
        ctrl = np.asarray(self.ctrl, dtype=float)
        jn = tuple(str(n) for n in np.asarray(self.joint_names).reshape(-1))
        an = tuple(str(n) for n in np.asarray(self.actuator_names).reshape(-1))
        t = len(time)
        if t < 10:
            raise ValueError(f"a log needs at least 10 samples, got {t}")
        for key, arr, n in (("qpos", qpos, len(jn)), ("ctrl", ctrl, len(an))):
            if arr.ndim == 1 and n == 1:
                arr = arr[:, None]
            if arr.shape != (t, n):
                raise ValueError(f"{key} must have shape (T={t}, {n}) to match time and its names, got {arr.shape}")
            object.__setattr__(self, key, arr)
        qpos, ctrl = self.qpos, self.ctrl
        for key, arr in (("time", time), ("qpos", qpos), ("ctrl", ctrl)):
            bad = ~np.isfinite(arr)
            if bad.any():
                row = int(np.argwhere(bad)[0][0])
                raise ValueError(f"{key} has {int(bad.sum())} NaN/inf values (first at sample {row}); "
                                 "drop or interpolate those samples before diagnosing")
        dt = np.diff(time)
        if np.any(dt <= 0):
            k = int(np.argmax(dt <= 0))
            raise ValueError(f"time must increase strictly; sample {k + 1} (t={time[k + 1]:.6g}) "
                             f"does not come after sample {k} (t={time[k]:.6g})")
        med = float(np.median(dt))
        if np.max(np.abs(dt - med)) > 0.25 * med:
            k = int(np.argmax(np.abs(dt - med)))
            raise ValueError(f"time must be uniformly sampled (median step {med:.6g} s, step {k} is {dt[k]:.6g} s); "
                             "resample the log onto a uniform grid first")
        for key, names in (("joint_names", jn), ("actuator_names", an)):
            if len(set(names)) != len(names):
                raise ValueError(f"{key} has duplicates: {sorted({n for n in names if names.count(n) > 1})}")
        object.__setattr__(self, "time", time)
        object.__setattr__(self, "joint_names", jn)
        object.__setattr__(self, "actuator_names", an)
        if self.qvel is not None:
            qvel = np.asarray(self.qvel, dtype=float).reshape(qpos.shape)
            if not np.all(np.isfinite(qvel)):
                raise ValueError("qvel has NaN/inf values")
            object.__setattr__(self, "qvel", qvel)
        if self.ctrl_enabled is not None:
            en = np.asarray(self.ctrl_enabled, dtype=bool)
            if en.ndim == 1:
                en = np.repeat(en[:, None], len(an), axis=1)
            if en.shape != ctrl.shape:
                raise ValueError(f"ctrl_enabled must have shape {ctrl.shape}, got {en.shape}")
            object.__setattr__(self, "ctrl_enabled", en)

    @property
    def dt(self) -> float:
        """The sampling period (median step) in seconds."""
        return float(np.median(np.diff(self.time)))

    @property
    def duration(self) -> float:
        return float(self.time[-1] - self.time[0])

    def slice(self, start: int, stop: int) -> RealLog:
        """Samples ``start:stop`` (used for time splits such as 70 % fit / 30 % test)."""
        sl = slice(start, stop)
        return replace(self, time=self.time[sl], qpos=self.qpos[sl], ctrl=self.ctrl[sl],
                       qvel=None if self.qvel is None else self.qvel[sl],
                       ctrl_enabled=None if self.ctrl_enabled is None else self.ctrl_enabled[sl],
                       meta={**self.meta, "slice": [int(start), int(stop)]})

    def holdout_blocks(self, fraction: float, blocks: int = 1) -> tuple[list[RealLog], list[RealLog]]:
        """The log cut into ``blocks`` equal parts, each split into its first ``1 - fraction``
        (fitted) and the rest (held out): the fitted parts and the held-out parts, in time order.
        One block is the plain time split; several spread the held-out samples over the log, so
        that a log whose excitation changes over time (a frequency sweep) is not judged only on
        its end."""
        if blocks < 1:
            raise ValueError(f"holdout blocks must be at least 1, got {blocks}")
        if not 0.0 < fraction < 1.0:
            raise ValueError(f"holdout fraction must be in (0, 1), got {fraction}")
        edges = np.round(np.linspace(0, len(self.time), blocks + 1)).astype(int)
        cuts = np.round(edges[:-1] + (1.0 - fraction) * np.diff(edges)).astype(int)
        if np.any(cuts - edges[:-1] < 10) or np.any(edges[1:] - cuts < 10):
            raise ValueError(f"{blocks} holdout blocks of {len(self.time)} samples leave a part shorter than "
                             f"10 samples; use fewer blocks")
        return ([self.slice(int(a), int(c)) for a, c in zip(edges[:-1], cuts)],
                [self.slice(int(c), int(b)) for c, b in zip(cuts, edges[1:])])


def save_log(log: RealLog, path: str | Path) -> Path:
    """Write ``log`` as the npz format (atomically: temp file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"format_version": np.asarray(FORMAT_VERSION), "time": log.time, "qpos": log.qpos, "ctrl": log.ctrl,
              "joint_names": np.asarray(log.joint_names), "actuator_names": np.asarray(log.actuator_names),
              "meta": np.asarray(json.dumps(log.meta))}
    if log.qvel is not None:
        arrays["qvel"] = log.qvel
    if log.ctrl_enabled is not None:
        arrays["ctrl_enabled"] = log.ctrl_enabled
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    return path


def load_log(path: str | Path) -> RealLog:
    """Read a log npz written by :func:`save_log` or by the user's own recorder."""
    path = Path(path)
    z = read_npz(path, "real-log npz")
    missing = [k for k in ("time", "qpos", "ctrl", "joint_names", "actuator_names") if k not in z]
    if missing:
        raise ValueError(f"{path} is not a real-log npz: missing {missing} "
                         "(expected time, qpos, ctrl, joint_names, actuator_names, optional qvel)")
    meta = json.loads(str(z["meta"])) if "meta" in z else {}
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: meta must be a JSON object, got {type(meta).__name__}")
    names = {k: tuple(str(n) for n in np.atleast_1d(z[k])) for k in ("joint_names", "actuator_names")}
    return RealLog(time=z["time"], qpos=z["qpos"], ctrl=z["ctrl"], joint_names=names["joint_names"],
                   actuator_names=names["actuator_names"], qvel=z["qvel"] if "qvel" in z else None,
                   ctrl_enabled=z["ctrl_enabled"] if "ctrl_enabled" in z else None,
                   meta={**meta, "source": str(path)})


def validate_against_model(log: RealLog, model: mujoco.MjModel) -> None:
    """Check that ``log`` can be replayed on ``model``: names exist, joints are scalar,
    and values are in the model's units (radians, not degrees).

    Raises:
        ValueError: naming the first problem found and what was expected.
    """
    for name in log.joint_names:
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            known = [model.joint(i).name for i in range(model.njnt)]
            raise ValueError(f"log joint {name!r} is not in the model; the model's joints are {known}")
        if model.jnt_type[jid] not in _SCALAR_JOINTS:
            raise ValueError(f"log joint {name!r} is a free/ball joint; logs hold scalar (hinge/slide) joints only")
    for name in log.actuator_names:
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, name) < 0:
            known = [model.actuator(i).name for i in range(model.nu)]
            raise ValueError(f"log actuator {name!r} is not in the model; the model's actuators are {known}")
    for k, name in enumerate(log.joint_names):
        jid = model.joint(name).id
        if model.jnt_type[jid] != int(mujoco.mjtJoint.mjJNT_HINGE):
            continue
        q = log.qpos[:, k]
        if np.max(np.abs(q)) > 4 * np.pi:
            raise ValueError(f"joint {name!r} reaches {np.max(np.abs(q)):.1f}: hinge angles must be in radians "
                             "(this looks like degrees; multiply by pi/180)")
        if model.jnt_limited[jid]:
            lo, hi = model.jnt_range[jid]
            margin = 0.2 * (hi - lo) + 0.05
            if q.min() < lo - margin or q.max() > hi + margin:
                raise ValueError(f"joint {name!r} spans [{q.min():.3f}, {q.max():.3f}] rad, far outside its range "
                                 f"[{lo:.3f}, {hi:.3f}]: wrong units, offset or joint order?")
