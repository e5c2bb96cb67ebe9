"""Fit the parameters of an effect (or a combination) to replay windows.

Least squares on the windowed position residual (optionally each window counted by a soft-L1
loss above the noise, so that one diverging replay does not steer a fit) by Levenberg-Marquardt,
so that every Jacobian (one perturbed model per parameter) is one batched rollout. Parameters
that act on one joint each get a diagonal Jacobian from a single perturbed rollout; beside other
effects, a per-joint effect's parameters on chains that move independently (the legs of a fixed
base) are perturbed in the same model, each read on its own chain. Two solvers share
that Jacobian: MuJoCo's ``mujoco.minimize.least_squares`` (one trial step per rollout, its
regulariser adapted from the predicted reduction) and the project's own (three damping
values tried in one batched rollout per iteration); ``benchmarks/gap_lm.py`` compares them.
Non-convex effects (delays, saturation, backlash) start from several points, all evaluated
at once. Confidence intervals come from a sandwich covariance clustered by window, because
the residuals inside a window are strongly correlated.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, Literal, get_args

import mujoco
import numpy as np
from mujoco import minimize

from crisp_gym.sim2real.effects import Effect, Param, Signals
from crisp_gym.sim2real.replay import Replayer, SimInputs, Trajectory


class Combo:
    """One or more effects applied together, with their parameters concatenated."""

    def __init__(self, effects: tuple[Effect, ...], ref: Trajectory) -> None:
        if sum(e.adds_state for e in effects) > 1:
            raise ValueError(f"at most one effect of a combination may extend the model: {[e.label for e in effects]}")
        self.effects = effects
        self.ref = ref
        self._params = [e.params(ref) for e in effects]
        self.sizes = [len(p) for p in self._params]

    @property
    def label(self) -> str:
        return " + ".join(e.label for e in self.effects)

    @property
    def family(self) -> str:
        return "+".join(sorted({e.family for e in self.effects}))

    @property
    def params(self) -> list[Param]:
        return [p for ps in self._params for p in ps]

    def split(self, x: np.ndarray) -> list[np.ndarray]:
        return np.split(np.asarray(x, dtype=float), np.cumsum(self.sizes)[:-1])

    def starts(self) -> list[np.ndarray]:
        """Multi-start grid: every effect's starts, combined one-by-one (not a product)."""
        per = [e.starts(self.ref) for e in self.effects]
        n = max(len(p) for p in per)
        return [np.concatenate([p[min(i, len(p) - 1)] for p in per]) for i in range(n)]

    def inputs(self, x: np.ndarray, trajs: list[Trajectory]) -> SimInputs:
        """The models and signals of every trajectory with the effects applied at ``x``."""
        parts = self.split(x)
        models, ctrl, qpos, qvel, friction, start = [], [], [], [], [], []
        extending = [e for e in self.effects if e.adds_state]
        for tr in trajs:
            model = extending[0].extended_model(tr) if extending else tr.model
            if any(e.touches_model for e in self.effects):
                model = model.__copy__()
                for e, xe in zip(self.effects, parts):
                    e.edit_model(model, xe, tr)
                if any(e.changes_inertia for e in self.effects):
                    # body_subtreemass and the other derived constants the dynamics read
                    # (a heavier link with a stale subtree mass gets a wrong mass matrix)
                    mujoco.mj_setConst(model, mujoco.MjData(model))
            sig = Signals(tr.ctrl, tr.log.qpos, tr.qvel)
            for e, xe in zip(self.effects, parts):
                sig = e.edit_signals(sig, xe, tr)
            models.append(model)
            ctrl.append(sig.ctrl)
            qpos.append(sig.qpos)
            qvel.append(sig.qvel)
            items = [(e, xe) for e, xe in zip(self.effects, parts) if e.state_friction]
            friction.append(partial(_state_friction, items, tr, model, sig.ctrl) if items else None)
            start.append(next((partial(e.start_state, xe, tr, model, sig.ctrl) for e, xe in zip(self.effects, parts)
                               if e.adds_state), None))
        return SimInputs(models, ctrl, qpos, qvel, friction, start)


class Frozen(Effect):
    """An effect held at fitted parameters ``x``: it acts as ``effect`` does but has no parameters,
    so that a combination can be replayed, or another effect fitted, with that part held (each
    part's share of what a combination removes)."""

    def __init__(self, effect: Effect, x: np.ndarray) -> None:
        super().__init__(effect.joints, per_joint=False)
        self.effect, self.x = effect, np.asarray(x, dtype=float)
        self.name, self.family = effect.name, effect.family
        self.touches_model, self.state_friction = effect.touches_model, effect.state_friction
        self.adds_state = effect.adds_state
        self.changes_inertia = effect.changes_inertia

    @property
    def label(self) -> str:
        return self.effect.label

    def params(self, tr: Trajectory) -> list[Param]:
        return []

    def edit_model(self, model, x: np.ndarray, tr: Trajectory) -> None:
        self.effect.edit_model(model, self.x, tr)

    def edit_signals(self, sig: Signals, x: np.ndarray, tr: Trajectory) -> Signals:
        return self.effect.edit_signals(sig, self.x, tr)

    def measure(self, qpos: np.ndarray, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        return self.effect.measure(qpos, self.x, tr)

    def measure_velocity(self, qvel: np.ndarray, x: np.ndarray, tr: Trajectory) -> np.ndarray:
        return self.effect.measure_velocity(qvel, self.x, tr)

    def friction(self, x, tr, model, ctrl, enabled, qpos, qvel) -> np.ndarray:
        return self.effect.friction(self.x, tr, model, ctrl, enabled, qpos, qvel)

    def extended_model(self, tr: Trajectory) -> mujoco.MjModel:
        return self.effect.extended_model(tr)

    def start_state(self, x: np.ndarray, tr: Trajectory, model: mujoco.MjModel, ctrl: np.ndarray,
                    states: np.ndarray, samples: np.ndarray) -> np.ndarray:
        return self.effect.start_state(self.x, tr, model, ctrl, states, samples)


def _state_friction(items: list[tuple[Effect, np.ndarray]], tr: Trajectory, model, ctrl: np.ndarray,
                    idx: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """The summed state-dependent friction of ``items`` at samples ``idx`` (a
    :data:`~crisp_gym.sim2real.replay.FrictionFn` once bound to a trajectory)."""
    u, enabled = ctrl[idx * tr.nsub], tr.enabled[idx]
    return sum(e.friction(xe, tr, model, u, enabled, qpos, qvel) for e, xe in items)


def residuals(replayer: Replayer, inputs: list[SimInputs]) -> np.ndarray:
    """(ncand, nwin, size - 1, n) prediction minus log, zero outside the windows."""
    pred = replayer.simulate(inputs)
    out = np.empty_like(pred)
    for c, inp in enumerate(inputs):
        out[c] = pred[c] - replayer.targets(inp)
    return out * replayer.mask[None, :, :, None]


def soft_l1_windows(r: np.ndarray, mask: np.ndarray, scale: float) -> np.ndarray:
    """Residuals (..., nwin, size - 1, n) rescaled window by window so that each window's sum of
    squares becomes ``count · scale² · ρ(e)``, where ``e`` is its mean square over ``scale²``
    and ``ρ(e) = 2 (√(1 + e) − 1)`` the soft-L1 loss (``e`` for small ``e``, ``2 √e`` for large)."""
    count = mask.sum(axis=1) * r.shape[-1] * scale**2
    e = np.sum(r**2, axis=(-2, -1)) / np.maximum(count, 1e-300)
    weight = np.where(e > 1e-12, 2 * (np.sqrt(1 + e) - 1) / np.maximum(e, 1e-12), 1.0)
    return r * np.sqrt(weight)[..., None, None]


def gap_rms(r: np.ndarray, mask: np.ndarray) -> float:
    """Root mean square of a residual over the samples inside windows."""
    return float(np.sqrt(np.sum(r**2) / (mask.sum() * r.shape[-1])))


@dataclass
class FitResult:
    """Fitted parameters, the training gap and how many window rollouts it took."""

    x: np.ndarray
    train_gap: float
    rollouts: int


class _Converged(Exception):
    """Raised from ``least_squares``'s iteration callback to stop it once its gain is negligible."""


Solver = Literal["mujoco", "batched"]
"""Levenberg-Marquardt of :class:`Fitter`: ``"mujoco"`` (``mujoco.minimize.least_squares``) or
``"batched"`` (three damping values per iteration in one batched rollout)."""


class Fitter:
    """Levenberg-Marquardt over batched replays of a fixed set of windows."""

    def __init__(self, replayer: Replayer, max_iter: int = 15, restarts: int = 2,
                 solver: Solver = "mujoco", step_fraction: float = 0.03, blockwise: bool = False,
                 robust_scale: float | None = None, window_scale: np.ndarray | None = None) -> None:
        """``restarts``: fresh-damping restarts of the batched solver after it stops.
        ``step_fraction``: each parameter's finite-difference step is at least this fraction
        of its range. Contacts (a foot's impacts, an end stop) make a replay's cost rugged on
        fine scales: on a stamping leg the training gap moves by 5 %, and not monotonically,
        when a payload's offset moves by 1 mm. A secant across a few per cent of the range
        follows the cost's slope where a fine step reads its roughness and stalls.
        ``blockwise``: beside other effects, too, a per-joint effect's derivatives come from
        one perturbed rollout, each parameter's on its own joint only (as they do when every
        fitted effect is per-joint): the cross-joint terms are dropped, and the Jacobian of a
        per-joint effect beside another costs two rollouts, not one per parameter.
        ``robust_scale`` (rad): each window enters the cost by the soft-L1 loss of its mean
        square over ``robust_scale²`` (:func:`soft_l1_windows`), quadratic below that scale and
        linear in the window's RMS above it. Where a replay is chaotic (a stamping foot), one
        window whose contact events a small change flips can hold most of the squared residual,
        and least squares then trades every other window's fit for it; counted by its RMS it
        steers the fit less. ``None``: plain least squares.
        ``window_scale`` (nwin,): each window's residual is multiplied by its entry before the
        loss (:func:`~crisp_gym.sim2real.diagnose.noise_weights`: a window whose replay noise
        alone makes diverge counts less). The reported training gap undoes both rescalings."""
        if solver not in get_args(Solver):
            raise ValueError(f"unknown solver {solver!r}; expected one of {get_args(Solver)}")
        if not 0.0 <= step_fraction < 1.0:
            raise ValueError(f"step_fraction must be in [0, 1), got {step_fraction}")
        if robust_scale is not None and not robust_scale > 0:
            raise ValueError(f"robust_scale must be positive (or None), got {robust_scale}")
        if window_scale is not None and (np.shape(window_scale) != (len(replayer.windows),)
                                         or not np.all(np.asarray(window_scale) > 0)):
            raise ValueError(f"window_scale must be positive, one per window ({len(replayer.windows)}), "
                             f"got shape {np.shape(window_scale)}")
        self.rep = replayer
        self.max_iter = max_iter
        self.restarts = restarts
        self.solver = solver
        self.step_fraction = step_fraction
        self.blockwise = blockwise
        self.robust_scale = robust_scale
        self.window_scale = window_scale
        self.rollouts = 0

    def on(self, replayer: Replayer, max_iter: int, **overrides: Any) -> Fitter:
        """A fitter with this one's settings (solver, steps, window loss and scales, restarts,
        blockwise derivatives; ``overrides`` replace any of them) on ``replayer``, whose windows
        must be this one's (a screen of the same logs, refits of resynthesised ones)."""
        settings = {"restarts": self.restarts, "solver": self.solver, "step_fraction": self.step_fraction,
                    "blockwise": self.blockwise, "robust_scale": self.robust_scale, "window_scale": self.window_scale}
        return Fitter(replayer, max_iter, **{**settings, **overrides})

    def _res(self, combo: Combo, xs: list[np.ndarray]) -> np.ndarray:
        """The residuals the fit minimises the squares of, at each of ``xs``."""
        self.rollouts += len(xs) * len(self.rep.windows)
        r = residuals(self.rep, [combo.inputs(x, self.rep.trajs) for x in xs])
        if self.window_scale is not None:
            r *= self.window_scale[:, None, None]
        return r if self.robust_scale is None else soft_l1_windows(r, self.rep.mask, self.robust_scale)

    def _gap(self, r: np.ndarray) -> float:
        """The plain RMS gap of one fitted residual ``r`` (the rescalings undone window by window)."""
        squares = np.sum(r**2, axis=(1, 2))
        if self.robust_scale is not None:
            count = self.rep.mask.sum(axis=1) * r.shape[-1] * self.robust_scale**2
            loss = squares / np.maximum(count, 1e-300)
            squares = ((loss / 2 + 1) ** 2 - 1) * count  # the inverse of the soft-L1 loss
        if self.window_scale is not None:
            squares = squares / self.window_scale**2
        return float(np.sqrt(np.sum(squares) / (self.rep.mask.sum() * r.shape[-1])))

    def _cost(self, r: np.ndarray) -> np.ndarray:
        return np.sum(r.reshape(r.shape[0], -1) ** 2, axis=1)

    def _columns(self, combo: Combo) -> np.ndarray | None:
        """When every effect with parameters has one per joint, on joints of its own, the
        residual column each parameter acts on (held effects, :class:`Frozen`, have none)."""
        fitted = [e for e, n in zip(combo.effects, combo.sizes) if n]
        if not fitted or not all(e.per_joint for e in fitted):
            return None
        cols = np.concatenate([e.columns(combo.ref) for e in fitted])
        return cols if len(cols) == len(combo.params) and len(np.unique(cols)) == len(cols) else None

    def fit(self, combo: Combo, starts: list[np.ndarray] | None = None) -> FitResult:
        """Fit ``combo`` from the best of ``starts`` (default: its own multi-start grid)."""
        params = combo.params
        lo = np.array([p.lo for p in params])
        hi = np.array([p.hi for p in params])
        step = np.maximum([p.step for p in params], self.step_fraction * (hi - lo))
        starts = [np.clip(s, lo, hi) for s in (starts or combo.starts())]
        before = self.rollouts
        r_all = self._res(combo, starts)
        costs = self._cost(r_all)
        best = None
        for k in np.argsort(costs)[:max(e.refine for e in combo.effects) if combo.effects else 1]:
            x, r, cost = self._descend(combo, starts[k], r_all[k], costs[k], lo, hi, step)
            # the batched solver's fresh damping: it stalls early on rugged (contact) costs; MuJoCo's
            # lowers its regulariser exponentially after each success, and a restart measured no better
            for _ in range(self.restarts if self.solver == "batched" else 0):
                x2, r2, c2 = self._descend(combo, x, r, cost, lo, hi, step, patience=1)
                if c2 >= cost * (1 - 1e-3):
                    break
                x, r, cost = x2, r2, c2
            if best is None or cost < best[2]:
                best = (x, r, cost)
        x, r, _ = best
        return FitResult(x=x, train_gap=self._gap(r), rollouts=self.rollouts - before)

    def _jacobian(self, combo: Combo, x: np.ndarray, r: np.ndarray, cols: np.ndarray | None,
                  step: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Forward differences of the residual ``r`` at ``x``, by steps of ``step`` (backward at
        the upper bound): (nwin, size-1, P) on the parameters' own columns ``cols`` when each
        acts on one joint (one perturbed rollout), else (P, nwin, size-1, n), with each
        :meth:`_blocks` block's from one perturbed rollout."""
        h = _signed_steps(x, step, hi)
        if cols is not None:
            rp = self._res(combo, [x + h])[0]
            return (rp[..., cols] - r[..., cols]) / h
        blocks = self._blocks(combo)
        points = [x + np.where(np.isin(np.arange(len(x)), idx), h, 0.0) for idx, _ in blocks]
        jac = np.zeros((len(x),) + r.shape)
        for (idx, own), rp in zip(blocks, self._res(combo, points)):
            if own is None:
                jac[idx[0]] = (rp - r) / h[idx[0]]
            else:
                for i, c in zip(idx, own):
                    jac[i][..., c] = (rp[..., c] - r[..., c]) / h[i]
        return jac

    def _blocks(self, combo: Combo) -> list[tuple[np.ndarray, list[np.ndarray] | None]]:
        """The parameters perturbed together by :meth:`_jacobian`, each block with the residual
        columns each of its parameters acts on. A per-joint effect's parameters (on joints of
        their own) share a rollout when their joints hang on independent chains (the legs of a
        fixed base: :func:`chains`), each read on its own chain's columns, which is exact but
        for contact between the chains (and not done under the robust loss, whose weight of a
        window mixes every column); with ``blockwise``, they all share one, each read on its own
        joint only (the cross-joint terms dropped). Every other parameter is a block alone, with
        every column."""
        offsets = np.cumsum([0] + combo.sizes[:-1])
        chain = chains(combo.ref) if self.robust_scale is None else np.zeros(len(combo.ref.dadr), dtype=int)
        blocks: list[tuple[np.ndarray, list[np.ndarray] | None]] = []
        for e, n, at in zip(combo.effects, combo.sizes, offsets):
            own = e.columns(combo.ref) if e.per_joint else None
            if own is None or len(own) != n or len(np.unique(own)) != n:
                blocks += [(np.array([at + i]), None) for i in range(n)]
            elif self.blockwise:
                blocks.append((at + np.arange(n), [np.array([c]) for c in own]))
            else:  # the k-th parameter of every chain in one rollout
                rank = np.array([np.sum(chain[own[:i]] == chain[c]) for i, c in enumerate(own)])
                blocks += [(at + idx, [np.flatnonzero(chain == chain[own[i]]) for i in idx])
                           for idx in (np.flatnonzero(rank == k) for k in range(rank.max() + 1))]
        return blocks

    def _descend(self, combo: Combo, x: np.ndarray, r: np.ndarray, cost: float, lo: np.ndarray, hi: np.ndarray,
                 step: np.ndarray, patience: int = 4) -> tuple[np.ndarray, np.ndarray, float]:
        """Levenberg-Marquardt from ``x`` (with residual ``r`` and ``cost`` there) by the
        fitter's solver; the batched one stops after ``max_iter`` iterations, a negligible
        gain, or ``patience`` failed steps in a row."""
        if self.solver == "mujoco":
            return self._least_squares(combo, x, r, cost, lo, hi, step)
        cols = self._columns(combo)
        mu = 1e-2
        failures = 0
        for _ in range(self.max_iter):
            if cols is not None:
                d = self._jacobian(combo, x, r, cols, step, hi)  # (nwin, size-1, P)
                g = np.einsum("wtp,wtp->p", d, r[..., cols])
                hess = np.einsum("wtp,wtp->p", d, d)
                steps = [-g / (hess * (1 + m) + 1e-300) for m in (mu / 10, mu, mu * 10)]
            else:
                jac = self._jacobian(combo, x, r, cols, step, hi).reshape(len(x), -1)
                hess = jac @ jac.T
                g = jac @ r.reshape(-1)
                diag = np.diag(np.diag(hess)) + 1e-12 * np.trace(hess) * np.eye(len(x)) + 1e-300 * np.eye(len(x))
                steps = [-np.linalg.solve(hess + m * diag, g) for m in (mu / 10, mu, mu * 10)]
            trials = [np.clip(x + s, lo, hi) for s in steps]
            rt = self._res(combo, trials)
            ct = self._cost(rt)
            k = int(np.argmin(ct))
            if ct[k] < cost:
                improvement = (cost - ct[k]) / cost
                x, r, cost = trials[k], rt[k], ct[k]
                mu = (mu / 10, mu, mu * 10)[k] / 3
                failures = 0
                if improvement < 1e-4:
                    break
            else:
                mu *= 100
                failures += 1
                if failures >= patience:
                    break
        return x, r, cost

    def _least_squares(self, combo: Combo, x: np.ndarray, r: np.ndarray, cost: float, lo: np.ndarray,
                       hi: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """``mujoco.minimize.least_squares`` from ``x`` with the fitter's Jacobian, its columns
        scaled to unit norm (Marquardt's scaling, as the batched solver's), stopped as the
        batched solver stops: after ``max_iter`` iterations or a negligible gain. Returns the
        best point it evaluated, with its residual and cost."""
        cols = self._columns(combo)
        best = [x, r, cost]

        def residual(xs: np.ndarray) -> np.ndarray:  # (P, k) points, one batched rollout
            if xs.shape[1] == 1 and np.array_equal(xs[:, 0], x):
                return r.reshape(-1, 1)  # the start, already simulated
            rs = self._res(combo, list(xs.T))
            costs = self._cost(rs)
            k = int(np.argmin(costs))
            if costs[k] < best[2]:
                best[:] = [xs[:, k].copy(), rs[k], costs[k]]
            return rs.reshape(len(rs), -1).T

        def jacobian(xc: np.ndarray, rc: np.ndarray) -> np.ndarray:  # (m, P)
            d = self._jacobian(combo, xc[:, 0], rc[:, 0].reshape(r.shape), cols, step, hi)
            if cols is None:
                return d.reshape(len(xc), -1).T
            full = np.zeros(r.shape + (len(cols),))
            full[..., cols, np.arange(len(cols))] = d
            return full.reshape(-1, len(cols))

        def stop_when_flat(trace: list[minimize.IterLog]) -> None:
            if trace[-1].reduction < 1e-4 * trace[-1].objective:
                raise _Converged

        try:
            # mu_factor 10: from the default 1.26, a failed step near the optimum climbed the
            # regulariser over a dozen extra rollouts; gtol relative to the start's residual
            minimize.least_squares(x, residual, bounds=[lo, hi], jacobian=jacobian, max_iter=self.max_iter,
                                   x_scale="jac", mu_factor=10.0, gtol=1e-3 * np.sqrt(cost), verbose=0,
                                   iter_callback=stop_when_flat)
        except _Converged:
            pass
        return best[0], best[1], best[2]

    def confidence(self, combo: Combo, x: np.ndarray, z: float = 1.96) -> np.ndarray:
        """Half-widths of the ``z``-sigma confidence intervals of ``x`` (sandwich
        covariance, clustered by replay window); infinite for the parameters the windows do
        not determine (:func:`undetermined`), to which the pseudo-inverse gives none."""
        params = combo.params
        lo = np.array([p.lo for p in params])
        hi = np.array([p.hi for p in params])
        r = self._res(combo, [x])[0]
        # at the parameters' own (fine) steps
        jac = self._jacobian(combo, x, r, None, np.array([p.step for p in params]), hi)  # (P, nwin, size-1, n)
        flat = jac.reshape(len(x), -1)
        bread = np.linalg.pinv(flat @ flat.T)
        scores = np.einsum("pwtj,wtj->wp", jac, r)
        meat = scores.T @ scores
        cov = bread @ meat @ bread
        half = z * np.sqrt(np.maximum(np.diag(cov), 0.0))
        return np.where(undetermined(flat, hi - lo), np.inf, half)


def _signed_steps(x: np.ndarray, step: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``step``, negated where a forward step would leave the upper bound ``hi``."""
    return np.where(x + step <= hi, step, -step)


def undetermined(jac: np.ndarray, span: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Which parameters the residual does not determine, from its Jacobian ``jac`` (P, m) and the
    parameters' ranges ``span`` (P,): those with a share in a direction along which moving across
    the whole range changes the residual by under ``tol`` of what the most telling direction's
    does (a payload's offset along a planar leg's hinge axis; two parameters that trade exactly)."""
    u, sv, _ = np.linalg.svd(jac * span[:, None], full_matrices=False)
    null = u[:, sv <= tol * max(float(sv.max(initial=0.0)), 1e-300)]
    return np.any(np.abs(null) > 1e-3, axis=1)


def chains(tr: Trajectory) -> np.ndarray:
    """For each logged joint, the root degree of freedom of the moving chain it hangs on. Joints
    on different roots (the legs of a fixed base) move independently unless they touch."""
    parent = tr.model.dof_parentid
    roots = []
    for d in tr.dadr:
        while parent[d] >= 0:
            d = parent[d]
        roots.append(d)
    return np.array(roots)
