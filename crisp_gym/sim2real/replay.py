"""Replay logged commands in simulation, in short windows re-synchronised to the log.

Each window starts from the logged state and is driven by the logged commands, so a
model error shows up as a local discrepancy instead of compounding over the whole log.
Every window of every candidate model runs in one :func:`mujoco.rollout.rollout` call
(one C call, threads, no Python per step), which is what makes fitting fast.

Time bases: the log has period ``dt``; the model steps ``nsub`` times per log sample
(``timestep = dt / nsub``). Commands live on that fine grid (sample-and-hold of the log),
so that signal effects such as a delay can shift them by fractions of a sample.

Friction that depends on the state (load-dependent, Stribeck) cannot live in a fixed
``MjModel``: such candidates are stepped one log sample at a time, each window with its own
model copy whose ``dof_frictionloss`` is set before every sample. In replay windows the
friction follows the *logged* state (the window stays close to it, as with the logged
initial velocity); in open loop (synthesis) it follows the simulated state.

A candidate model may have more state than the log's (a gear's rotor): its windows start
from the logged joints' state, the rest set by the candidate's :data:`StartFn`, and models
of each state layout run in a rollout of their own.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import mujoco
import numpy as np
from mujoco import rollout
from scipy.signal import savgol_coeffs, savgol_filter

from crisp_gym.sim2real.log import RealLog, validate_against_model

_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS


def smooth_derivative(q: np.ndarray, dt: float, window: int = 5) -> np.ndarray:
    """Velocity from positions by a quadratic Savitzky-Golay fit (robust to quantisation).

    Five samples: the replay windows start from these velocities, and a longer span biases
    them wherever the motion is not locally cubic (impacts, command steps); that bias, not
    the encoder noise, dominated the gap of exact models with seven samples."""
    window = min(window, len(q) - (1 - len(q) % 2))
    return savgol_filter(q, window, 2, deriv=1, delta=dt, axis=0, mode="interp")


def noise_sigma(q: np.ndarray, window: int = 9) -> np.ndarray:
    """Per-column measurement noise: the std of what a cubic Savitzky-Golay smoother
    removes, corrected for the share of the noise the smoother keeps (its centre weight)."""
    h0 = savgol_coeffs(window, 3)[window // 2]
    resid = q - savgol_filter(q, window, 3, axis=0, mode="interp")
    return np.std(resid, axis=0) / np.sqrt(1.0 - h0)


@contextmanager
def collected_warnings() -> Iterator[Counter[str]]:
    """MuJoCo's warnings inside the block, counted by message (numbers as ``N``) instead of printed
    and appended to ``MUJOCO_LOG.TXT`` in the working directory. Fits try parameters under which
    some windows diverge; MuJoCo resets those and warns each time, which is expected there. The
    previous handler is restored on exit."""
    counts: Counter[str] = Counter()
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda message: counts.update([re.sub(r"\d+(\.\d+)?", "N", message)]))
    try:
        yield counts
    finally:
        mujoco.set_mju_user_warning(previous)


@dataclass
class Trajectory:
    """A log bound to the model it is replayed on.

    ``ctrl`` is the full actuator command on the fine grid, (T * nsub, nu): actuators
    absent from the log keep command 0. ``enabled`` (T, nu) marks powered actuators.
    ``qvel`` is the logged velocity, or a smoothed derivative of the positions when the log
    has none; ``sigma`` / ``sigma_v`` the measurement noise of positions / logged velocities.
    ``spec`` is the model's source when it was given as an ``MjSpec`` (effects that add parts
    to the model, such as a gear's rotor, need it).
    """

    log: RealLog
    model: mujoco.MjModel
    nsub: int
    qadr: np.ndarray
    dadr: np.ndarray
    act: np.ndarray
    ctrl: np.ndarray
    enabled: np.ndarray
    qvel: np.ndarray
    sigma: np.ndarray
    sigma_v: np.ndarray | None = None
    spec: mujoco.MjSpec | None = None
    _variants: dict = field(default_factory=dict, repr=False)

    @property
    def fine_time(self) -> np.ndarray:
        h = self.log.dt / self.nsub
        return self.log.time[0] + h * np.arange(len(self.log.time) * self.nsub)

    def model_for(self, base: mujoco.MjModel, pattern: tuple[bool, ...]) -> mujoco.MjModel:
        """``base`` with the actuators that ``pattern`` marks off exerting no force."""
        if all(pattern):
            return base
        key = (id(base), pattern)
        if key not in self._variants:
            off = base.__copy__()
            for a, on in enumerate(pattern):
                if not on:
                    off.actuator_gainprm[a] = 0.0
                    off.actuator_biasprm[a] = 0.0
                    off.actuator_damping[a] = 0.0  # an open circuit: no back-EMF either
            self._variants[key] = (base, off)  # keep base alive so its id stays unique
        return self._variants[key][1]


def bind(log: RealLog, model: mujoco.MjModel | mujoco.MjSpec, validate: bool = True) -> Trajectory:
    """Validate ``log`` against ``model`` (unless it was synthesised from the model
    itself) and prepare it for replay. ``model`` may be an ``MjSpec``: it is compiled, and
    kept for the effects that add parts to the model."""
    spec = None
    if isinstance(model, mujoco.MjSpec):
        spec = model.copy()  # the caller may go on editing theirs
        model = spec.compile()
    if validate:
        validate_against_model(log, model)
    model = model.__copy__()
    dt = log.dt
    nsub = max(1, int(np.ceil(dt / model.opt.timestep - 1e-6)))
    model.opt.timestep = dt / nsub
    qadr = np.array([model.jnt_qposadr[model.joint(n).id] for n in log.joint_names], dtype=int)
    dadr = np.array([model.jnt_dofadr[model.joint(n).id] for n in log.joint_names], dtype=int)
    act = np.array([model.actuator(n).id for n in log.actuator_names], dtype=int)
    t = len(log.time)
    ctrl = np.zeros((t, model.nu))
    ctrl[:, act] = log.ctrl
    enabled = np.ones((t, model.nu), dtype=bool)
    if log.ctrl_enabled is not None:
        enabled[:, act] = log.ctrl_enabled
    qvel = log.qvel if log.qvel is not None else smooth_derivative(log.qpos, dt)
    return Trajectory(log=log, model=model, nsub=nsub, qadr=qadr, dadr=dadr, act=act,
                      ctrl=np.repeat(ctrl, nsub, axis=0), enabled=enabled, qvel=qvel, sigma=noise_sigma(log.qpos),
                      sigma_v=None if log.qvel is None else noise_sigma(log.qvel), spec=spec)


@dataclass(frozen=True)
class Windows:
    """Replay windows: trajectory index, first sample, sample count (incl. the initial
    state) and the enabled-actuator pattern, which is constant inside a window."""

    traj: np.ndarray
    start: np.ndarray
    length: np.ndarray
    pattern: tuple[tuple[bool, ...], ...]
    size: int

    def __len__(self) -> int:
        return len(self.traj)

    def subset(self, keep: np.ndarray) -> Windows:
        """The windows selected by ``keep`` (indices or a boolean mask)."""
        idx = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep, dtype=int)
        return Windows(self.traj[idx], self.start[idx], self.length[idx],
                       tuple(self.pattern[i] for i in idx), self.size)

    def mask(self) -> np.ndarray:
        """(nwin, size - 1) True where a predicted sample lies inside its window."""
        return np.arange(1, self.size)[None, :] < self.length[:, None]


def roughness(tr: Trajectory) -> np.ndarray:
    """(T,) how far the logged motion is from locally cubic around each sample (what a
    five-sample cubic fit leaves, in units of the noise, summed over joints): large at
    impacts and command steps, where a smoothed velocity is biased."""
    q = tr.log.qpos
    if len(q) < 5:
        return np.zeros(len(q))
    resid = (q - savgol_filter(q, 5, 3, axis=0, mode="interp")) / np.maximum(tr.sigma, 1e-9)[None]
    return np.sum(resid**2, axis=1)


def make_windows(trajs: list[Trajectory], window_s: float, stride_s: float | None = None,
                 shift_s: float = 0.05) -> Windows:
    """Tile every trajectory with windows of ``window_s`` seconds (``stride_s`` apart,
    default: back to back), cut where an actuator switches on or off. Each start moves by
    up to ``shift_s`` to the locally smoothest sample (see :func:`roughness`), because a
    window inherits the error of its initial velocity: one that starts on an impact
    replays badly even with the exact model."""
    if window_s <= 0:
        raise ValueError(f"window length must be positive, got {window_s}")
    dt = trajs[0].log.dt
    size = max(3, int(round(window_s / dt)) + 1)
    stride = max(1, int(round((stride_s or window_s) / dt)))
    reach = int(round(shift_s / dt))
    rows: list[tuple[int, int, int, tuple[bool, ...]]] = []
    for ti, tr in enumerate(trajs):
        en = tr.enabled
        rough = roughness(tr)
        cuts = np.flatnonzero(np.any(en[1:] != en[:-1], axis=1)) + 1
        bounds = np.concatenate([[0], cuts, [len(en)]])
        for a, b in zip(bounds[:-1], bounds[1:]):
            pattern = tuple(bool(x) for x in en[a])
            s = a
            while s + max(3, size // 2) <= b:
                lo, hi = max(a, s - reach), min(b - max(3, size // 2), s + reach)
                best = lo + int(np.argmin(rough[lo:hi + 1])) if hi >= lo else s
                rows.append((ti, best, min(size, b - best), pattern))
                s += stride
    if not rows:
        raise ValueError(f"no replay window of {window_s} s fits in the logs; use a shorter window")
    traj, start, length, pattern = zip(*rows)
    return Windows(np.array(traj), np.array(start), np.array(length), tuple(pattern), size)


FrictionFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
"""State-dependent dry friction: ``(sample indices (k,), positions (k, n), velocities
(k, n)) -> added frictionloss (k, n)`` on the logged joints' dofs."""

StartFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""Initial states of a model with more state than the log's: ``(full states (k, nstate) in the
model's layout, the logged joints already set; their log samples (k,)) -> the states with the
rest set``."""


@dataclass
class SimInputs:
    """What one candidate model feeds the replay, per trajectory: the models (before
    switching actuators off), fine-grid commands, the log seen in the model's frame
    (the initial states and the targets, after measurement effects are undone) and,
    where the candidate has state-dependent friction or state beyond the log's, its
    :data:`FrictionFn` or :data:`StartFn`."""

    models: list[mujoco.MjModel]
    ctrl: list[np.ndarray]
    qpos: list[np.ndarray]
    qvel: list[np.ndarray]
    friction: list[FrictionFn | None] | None = None
    start: list[StartFn | None] | None = None

    def friction_of(self, ti: int) -> FrictionFn | None:
        return None if self.friction is None else self.friction[ti]

    def start_of(self, ti: int) -> StartFn | None:
        return None if self.start is None else self.start[ti]


def nominal_inputs(trajs: list[Trajectory]) -> SimInputs:
    return SimInputs([t.model for t in trajs], [t.ctrl for t in trajs], [t.log.qpos for t in trajs],
                     [t.qvel for t in trajs])


def _layout_key(model: mujoco.MjModel) -> tuple[int, ...]:
    """Models with equal keys share a state layout (and can share one rollout call)."""
    return model.nq, model.nv, model.na, mujoco.mj_stateSize(model, _STATE)


class Replayer:
    """Runs windows of many candidates in one batched rollout (one per state layout)."""

    def __init__(self, trajs: list[Trajectory], windows: Windows, nthread: int = 2) -> None:
        names = trajs[0].log.joint_names
        for t in trajs[1:]:
            if t.log.joint_names != names or abs(t.log.dt - trajs[0].log.dt) > 1e-6 * trajs[0].log.dt:
                raise ValueError("all logs of one diagnosis must log the same joints at the same rate")
        self.trajs, self.windows = trajs, windows
        self.nsub = trajs[0].nsub
        self.nstep = (windows.size - 1) * self.nsub
        self.nthread = max(1, nthread)
        self._layouts: dict[tuple[int, ...], tuple[np.ndarray, list[mujoco.MjData]]] = {}
        self._qadr, self._dadr = trajs[0].qadr, trajs[0].dadr
        self.mask = windows.mask()
        offsets = np.arange(windows.size)
        self._idx = [np.minimum(windows.start[:, None] + offsets[None], len(t.log.time) - 1) for t in trajs]

    def _layout(self, model: mujoco.MjModel) -> tuple[np.ndarray, list[mujoco.MjData]]:
        """The default full state and the rollout datas of models of ``model``'s state layout."""
        key = _layout_key(model)
        if key not in self._layouts:
            datas = [mujoco.MjData(model) for _ in range(self.nthread)]
            template = np.zeros(mujoco.mj_stateSize(model, _STATE))
            mujoco.mj_getState(model, datas[0], template, _STATE)
            self._layouts[key] = template, datas
        return self._layouts[key]

    def _start_states(self, inp: SimInputs, ti: int, samples: np.ndarray) -> np.ndarray:
        """(k, nstate) full states at log samples ``samples`` in the layout of the candidate's model."""
        model = inp.models[ti]
        nq1 = 1 + model.nq
        out = np.tile(self._layout(model)[0], (len(samples), 1))
        out[:, 0] = self.trajs[ti].log.time[samples]
        out[:, 1 + self._qadr] = inp.qpos[ti][samples]
        out[:, nq1 + self._dadr] = inp.qvel[ti][samples]
        fn = inp.start_of(ti)
        return out if fn is None else fn(out, samples)

    def targets(self, inputs: SimInputs) -> np.ndarray:
        """(nwin, size - 1, n) the logged positions each window is compared with."""
        w = self.windows
        out = np.empty((len(w), w.size - 1, len(self._qadr)))
        for ti in range(len(self.trajs)):
            sel = w.traj == ti
            out[sel] = inputs.qpos[ti][self._idx[ti][sel, 1:]]
        return out

    def simulate(self, candidates: list[SimInputs]) -> np.ndarray:
        """Predicted positions (ncand, nwin, size - 1, n) of the logged joints."""
        w = self.windows
        nw, nc = len(w), len(candidates)
        init: list[np.ndarray] = [None] * (nc * nw)  # type: ignore[list-item]
        ctrl = np.empty((nc * nw, self.nstep, self.trajs[0].model.nu))
        models: list[mujoco.MjModel] = [None] * (nc * nw)  # type: ignore[list-item]
        fine = np.arange(self.nstep)
        stepped = np.zeros(nc * nw, dtype=bool)
        added = np.zeros((nc * nw, w.size - 1, len(self._qadr)))
        layouts: dict[tuple[int, ...], list[int]] = {}  # the rows of each state layout
        for c, inp in enumerate(candidates):
            for ti, tr in enumerate(self.trajs):
                sel = np.flatnonzero(w.traj == ti)
                if not len(sel):
                    continue
                rows = c * nw + sel
                layouts.setdefault(_layout_key(inp.models[ti]), []).extend(rows)
                s0 = w.start[sel]
                for r, k, state in zip(rows, sel, self._start_states(inp, ti, s0)):
                    init[r] = state
                    models[r] = tr.model_for(inp.models[ti], w.pattern[k])
                fidx = np.minimum(s0[:, None] * self.nsub + fine[None], len(inp.ctrl[ti]) - 1)
                ctrl[rows] = inp.ctrl[ti][fidx]
                fn = inp.friction_of(ti)
                if fn is not None:
                    idx = self._idx[ti][sel, :-1]
                    f = fn(idx.reshape(-1), inp.qpos[ti][idx].reshape(-1, len(self._qadr)),
                           inp.qvel[ti][idx].reshape(-1, len(self._dadr)))
                    added[rows] = f.reshape(len(sel), w.size - 1, -1)
                    stepped[rows] = True
        q = np.empty((nc * nw, w.size - 1, len(self._qadr)))
        for rows in map(np.array, layouts.values()):
            datas = self._layout(models[rows[0]])[1]
            states0 = np.stack([init[r] for r in rows])
            plain, rubbing = ~stepped[rows], stepped[rows]
            if plain.any():
                states, _ = rollout.rollout([models[r] for r in rows[plain]], datas, states0[plain], ctrl[rows[plain]],
                                            persistent_pool=True)
                q[rows[plain]] = states[:, self.nsub - 1::self.nsub, 1 + self._qadr]
            if rubbing.any():
                q[rows[rubbing]] = self._stepped([models[r] for r in rows[rubbing]], datas, states0[rubbing],
                                                 ctrl[rows[rubbing]], added[rows[rubbing]])
        return q.reshape(nc, nw, w.size - 1, -1)

    def _stepped(self, models: list[mujoco.MjModel], datas: list[mujoco.MjData], init: np.ndarray, ctrl: np.ndarray,
                 added: np.ndarray) -> np.ndarray:
        """Rollouts one log sample at a time, each row's frictionloss set to its nominal
        value plus ``added`` (rows, samples, n) before every sample. Only rows with friction
        to add get a model copy of their own (copying a model costs more than stepping it a sample)."""
        rubbing = np.flatnonzero(np.any(added != 0.0, axis=(1, 2)))
        own = list(models)
        for r in rubbing:
            own[r] = models[r].__copy__()
        base = [own[r].dof_frictionloss[self._dadr].copy() for r in rubbing]
        q = np.empty(added.shape)
        state = init
        for k in range(added.shape[1]):
            for r, b in zip(rubbing, base):
                own[r].dof_frictionloss[self._dadr] = np.maximum(b + added[r, k], 0.0)
            u = ctrl[:, k * self.nsub:(k + 1) * self.nsub]
            states, _ = rollout.rollout(own, datas, state, u, persistent_pool=True)
            state = states[:, -1]
            q[:, k] = state[:, 1 + self._qadr]
        return q

    def open_loop(self, inputs: SimInputs) -> list[np.ndarray]:
        """Each trajectory simulated from its first logged state to its end without
        re-synchronising (segments chained where actuators switch): (T, n) per log.

        Used for frequency responses and lags, which need uninterrupted signals."""
        return [q for q, _ in self.open_loop_states(inputs)]

    def open_loop_states(self, inputs: SimInputs) -> list[tuple[np.ndarray, np.ndarray]]:
        """Like :meth:`open_loop`, positions and velocities (T, n) per log: what
        synthesised logs (benchmark, noise floor) are made of."""
        out = []
        for ti, tr in enumerate(self.trajs):
            t_len = len(tr.log.time)
            q = np.empty((t_len, len(self._qadr)))
            v = np.empty((t_len, len(self._dadr)))
            q[0], v[0] = inputs.qpos[ti][0], inputs.qvel[ti][0]
            state = self._start_states(inputs, ti, np.array([0]))[0]
            nq1 = 1 + inputs.models[ti].nq
            data = self._layout(inputs.models[ti])[1][0]
            en = tr.enabled
            cuts = np.flatnonzero(np.any(en[1:] != en[:-1], axis=1)) + 1
            bounds = np.concatenate([[0], cuts, [t_len]])
            fn = inputs.friction_of(ti)
            for a, b in zip(bounds[:-1], bounds[1:]):
                n_samples = b - a if b < t_len else b - a - 1
                if n_samples <= 0:
                    continue
                model = tr.model_for(inputs.models[ti], tuple(bool(x) for x in en[a]))
                if fn is None:
                    u = inputs.ctrl[ti][a * self.nsub:(a + n_samples) * self.nsub][None]
                    states, _ = rollout.rollout(model, data, state[None], u)
                    q[a + 1:a + 1 + n_samples] = states[0, self.nsub - 1::self.nsub][:, 1 + self._qadr]
                    v[a + 1:a + 1 + n_samples] = states[0, self.nsub - 1::self.nsub][:, nq1 + self._dadr]
                    state = states[0, -1]
                    continue
                # State-dependent friction follows the simulated state, sample by sample.
                own = model.__copy__()
                base = own.dof_frictionloss[self._dadr].copy()
                for k in range(a, a + n_samples):
                    f = fn(np.array([k]), state[None, 1 + self._qadr], state[None, nq1 + self._dadr])[0]
                    own.dof_frictionloss[self._dadr] = np.maximum(base + f, 0.0)
                    u = inputs.ctrl[ti][k * self.nsub:(k + 1) * self.nsub][None]
                    states, _ = rollout.rollout(own, data, state[None], u)
                    state = states[0, -1]
                    q[k + 1], v[k + 1] = state[1 + self._qadr], state[nq1 + self._dadr]
            out.append((q, v))
        return out
