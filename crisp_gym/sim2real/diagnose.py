"""The diagnosis: where the gap lies, which effect explains it, how far it shrinks.

Every candidate effect is fitted on training windows and ranked by the gap it leaves on
held-out windows (other logs, or the last part of each log), with a penalty per parameter so
that a richer model must earn its keep. Two effects together come from forward selection
(every other effect fitted together with the best one for a few iterations and judged on the
held-out windows, the best of those pairs then fitted fully), and on multi-joint logs from
a per-joint mixture (each joint's best per-joint family, confined to those joints). Where the
log holds every degree of freedom of the model, every joint's Coulomb friction, damping,
armature and load friction are also fitted together, from a linear estimate on the torque the
logged motion needed (:mod:`~crisp_gym.sim2real.inverse`), and the effects the held-out data do
not need are pruned. The verdict compares gaps with the *noise floor*: the gap this same
pipeline measures on a log that the model itself produced, with the log's own measurement
noise. A log whose gap is at the floor gets "none"; a gap that no effect brings near the floor
is "unexplained".
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field, fields, replace
from typing import Any

import mujoco
import numpy as np
from scipy import stats
from tqdm import tqdm

from crisp_gym.sim2real.effects import CannotApply, Effect, Param, check_families, library
from crisp_gym.sim2real.fit import Combo, Fitter, Frozen, Solver, gap_rms, residuals
from crisp_gym.sim2real.gap import residual_structure, where
from crisp_gym.sim2real.inverse import JOINT_MODEL, joint_model_start
from crisp_gym.sim2real.log import RealLog
from crisp_gym.sim2real.replay import Replayer, Trajectory, bind, collected_warnings, make_windows, nominal_inputs


@dataclass(frozen=True)
class DiagnoseConfig:
    """Settings of diagnose.

    Attributes:
        window_s: replay window length (s); long enough to see the dynamics (a few PD
            time constants), short enough that errors do not compound.
        holdout_fraction: without held-out logs, this fraction of every log is held out.
        holdout_blocks: the held-out data is the last ``holdout_fraction`` of each of this many equal
            parts of the log (1: its end). Several spread the held-out data over a log whose
            excitation changes with time (a frequency sweep), where the end alone would also
            test how the fit extrapolates to the fastest moves.
        bases: forward selection holds each of this many best single effects (of distinct
            families; and a richer form of an effect ranked above the last of them,
            :func:`forward_bases`) and screens every other effect on top of it.
        pairs: forward selection fits this many of the best screened pairs jointly.
        screen_iter: Levenberg-Marquardt iterations of each screening fit (an effect fitted
            together with one of the best, both from their single fits).
        later_base_partners: the bases after the best one screen only this many of the best
            single effects on top of them (the best base screens every one): it keeps a
            30 s, 12-joint log within two minutes.
        refine_top: an effect that nests a simpler one (gearbox friction nests load friction)
            is fitted only where that one is among this many best single effects.
        penalty: per extra parameter, the relative increase of the squared held-out gap a
            candidate is charged in the ranking.
        none_factor: a held-out gap below none_factor x the noise floor means "none".
        explained_factor: the winner explains the gap if it leaves at most this x the floor.
        max_iter: Levenberg-Marquardt iterations per fit.
        step_fraction: the fits' finite-difference steps are at least this fraction of each
            parameter's range (:class:`~crisp_gym.sim2real.fit.Fitter`): contacts make the
            replay's cost rugged on finer scales.
        robust_scale: if positive, the fits count each replay window by the soft-L1 loss of its
            mean square, at this many nominal noise floors (:class:`~crisp_gym.sim2real.fit.Fitter`):
            a window whose replay diverges (or whose log jumps) counts by its RMS, not its square.
            0 (the default): plain least squares; ``docs/sim2real.md`` says when to use it.
        noise_weights: if true, the fits count each training window in proportion to how well
            the nominal model replays it under noise alone (:func:`noise_weights`): where a
            contact's timing flips with the noise (a stamping foot), a window diverges whatever
            the parameters, and least squares would trade every other window's fit for it.
            Windows that replay as reliably as the typical one keep their full weight, so
            models without such events are fitted as before. Off by default.
        inverse_dynamics: also fit every joint's Coulomb friction, damping, armature and load
            friction together, from their linear estimate on the torque the logged motion needed
            (:mod:`~crisp_gym.sim2real.inverse`; skipped, with the reason, where the log lacks a
            degree of freedom of the model; left out where ``families`` does not hold all four).
        solver: the fits' Levenberg-Marquardt (:data:`~crisp_gym.sim2real.fit.Solver`):
            ``"mujoco"`` (``mujoco.minimize.least_squares``, 40 % fewer rollouts over the
            bench's models, ``benchmarks/gap_lm.py``) or ``"batched"`` (the project's own).
        nthread: rollout threads.
        seed: seed of the noise-floor synthesis.
        families: restrict the library to these effect families (empty: all).
        tolerance: a simpler candidate (fewer parameters, or as many in fewer effects) replaces
            the best one when their squared held-out gaps differ by less than tolerance x the
            squared floor (the larger of the nominal model's and the best candidate's median
            draws): below the noise, a richer model has not earned its parameters. A pair or
            mixture is kept only if leaving out any one part raises its squared training gap by
            at least tolerance x :func:`noise_spread` of the nominal model's draws.
        bootstrap: refits for the parametric-bootstrap intervals of an explained winner
            (fewer than 3: the sandwich covariance, which ignores the bias of replay fits).
        floor_draws: noise draws of the noise floors: the median draw is the nominal
            model's floor (for "none"), the largest the best candidate's (for "explained");
            the best candidate's median draw sets the parsimony tolerance.
        show_progress: tqdm progress over the fits.
    """

    window_s: float = 0.5
    holdout_fraction: float = 0.3
    holdout_blocks: int = 1
    bases: int = 2
    pairs: int = 3
    screen_iter: int = 3
    later_base_partners: int = 8
    refine_top: int = 3
    penalty: float = 0.02
    none_factor: float = 1.5
    explained_factor: float = 1.6
    max_iter: int = 15
    step_fraction: float = 0.03
    robust_scale: float = 0.0
    noise_weights: bool = False
    inverse_dynamics: bool = True
    solver: Solver = "mujoco"
    nthread: int = 2
    seed: int = 0
    families: tuple[str, ...] = ()
    tolerance: float = 1.0
    bootstrap: int = 6
    floor_draws: int = 5
    show_progress: bool = True

    def __post_init__(self) -> None:
        check_families(self.families)
        if not 0.0 < self.holdout_fraction < 1.0 or self.holdout_blocks < 1:
            raise ValueError(f"holdout_fraction must be in (0, 1) and holdout_blocks at least 1, got "
                             f"{self.holdout_fraction} and {self.holdout_blocks}")
        if not 0.0 <= self.step_fraction < 1.0:
            raise ValueError(f"step_fraction must be in [0, 1), got {self.step_fraction}")
        if self.robust_scale < 0:
            raise ValueError(f"robust_scale must be non-negative, got {self.robust_scale}")


@dataclass
class Candidate:
    """A fitted effect (or pair): parameters, training gap, held-out gap (overall and per
    joint) and ranking score."""

    combo: Combo
    x: np.ndarray
    train_gap: float
    heldout_gap: float = float("nan")
    heldout_per_joint: np.ndarray | None = None
    score: float = float("nan")

    @property
    def nparam(self) -> int:
        return len(self.x)


def _split(pairs: list[tuple[RealLog, mujoco.MjModel | mujoco.MjSpec]], fraction: float, blocks: int):
    train, test = [], []
    for log, model in pairs:
        fitted, held = log.holdout_blocks(fraction, blocks)
        train += [(part, model) for part in fitted]
        test += [(part, model) for part in held]
    return train, test


HELDOUT_LOGS = "held-out logs"
"""``Diagnosis.heldout`` when the held-out data were logs of their own (not a split of the fitted ones)."""


def _heldout_label(cfg: DiagnoseConfig) -> str:
    share = f"the last {100 * cfg.holdout_fraction:.0f} % of"
    if cfg.holdout_blocks == 1:
        return f"{share} every log"
    return f"{share} each of {cfg.holdout_blocks} equal parts of every log"


def speed_ratio(fitted: list[RealLog], heldout: list[RealLog]) -> float:
    """How fast the held-out logs' joints move against the fitted ones': the median over joints
    of the ratio of their mean absolute speeds (finite differences of the positions). Far from 1,
    the held-out gap also measures how the fitted model extrapolates."""
    def mean_speed(logs: list[RealLog]) -> np.ndarray:
        steps = np.concatenate([np.abs(np.diff(lg.qpos, axis=0)) / np.diff(lg.time)[:, None] for lg in logs])
        return steps.mean(axis=0)
    return float(np.median(mean_speed(heldout) / np.maximum(mean_speed(fitted), 1e-12)))


def resynthesize(rep: Replayer, combo: Combo, x: np.ndarray, rng: np.random.Generator) -> list[Trajectory]:
    """The logs of ``rep`` as the model ``combo`` at ``x`` would have produced them: same
    commands and initial states, seen through its sensor effects, with each log's estimated
    measurement noise added."""
    synth = rep.open_loop_states(combo.inputs(x, rep.trajs))
    trajs = []
    for tr, (q, v) in zip(rep.trajs, synth):
        for e, xe in zip(combo.effects, combo.split(x)):
            q, v = e.measure(q, xe, tr), e.measure_velocity(v, xe, tr)
        noisy = q + rng.normal(0.0, 1.0, q.shape) * tr.sigma[None]
        # Logged velocities are synthesised too, with their own noise; else they are derived.
        qvel = None if tr.sigma_v is None else v + rng.normal(0.0, 1.0, v.shape) * tr.sigma_v[None]
        trajs.append(replace(bind(replace(tr.log, qpos=noisy, qvel=qvel), tr.model, validate=False), spec=tr.spec))
    return trajs


def _noise_residuals(rep: Replayer, seed: int, candidate: Candidate | None, draws: int) -> Iterator[np.ndarray]:
    """The windowed residuals (nwin, size-1, J) of the nominal model (or ``candidate``'s) on
    ``draws`` logs it resynthesises itself (:func:`resynthesize`): what noise alone leaves."""
    combo = candidate.combo if candidate is not None else Combo((), rep.trajs[0])
    x = candidate.x if candidate is not None else np.zeros(0)
    for k in range(draws):
        trajs = resynthesize(rep, combo, x, np.random.default_rng(seed + k))
        yield residuals(Replayer(trajs, rep.windows, rep.nthread), [combo.inputs(x, trajs)])[0]


def noise_floors(rep: Replayer, seed: int, candidate: Candidate | None = None, draws: int = 5) -> np.ndarray:
    """Per-joint windowed gap (draws, J) on the logs :func:`resynthesize` makes with the nominal
    model (or ``candidate``'s), one row per noise draw, from the smallest overall RMS to the
    largest: the gap this pipeline measures when the model is exactly right.

    That gap is heavy-tailed (with contacts, one unlucky noise draw can make a window
    diverge), so several draws are made: the median one (:func:`median_draw`) is the
    typical floor, the last the largest the exact model produces."""
    floors = np.array([np.sqrt(np.sum(r**2, axis=(0, 1)) / rep.mask.sum())
                       for r in _noise_residuals(rep, seed, candidate, draws)])
    return floors[np.argsort(np.mean(floors**2, axis=1))]


def noise_weights(rep: Replayer, seed: int, draws: int = 5) -> np.ndarray:
    """(nwin,) each window's weight in the fits: 1 / sqrt(its mean square under noise alone over
    the median window's), at most 1. Generalised least squares' weights by each window's noise
    variance (over ``draws`` draws of :func:`_noise_residuals`, the nominal model's), capped
    so that no window counts more than the typical one: a window whose contacts flip with the
    noise counts less, the others as before."""
    counts = np.maximum(rep.mask.sum(axis=1), 1)
    mean_square = np.mean([np.sum(r**2, axis=(1, 2)) / (counts * r.shape[-1])
                           for r in _noise_residuals(rep, seed, None, draws)], axis=0)
    return 1.0 / np.sqrt(np.maximum(mean_square / max(np.median(mean_square), 1e-300), 1.0))


def median_draw(floors: np.ndarray) -> np.ndarray:
    """The median row of :func:`noise_floors` (the lower middle one of an even count)."""
    return floors[(len(floors) - 1) // 2]


def _overall(floor_j: np.ndarray) -> float:
    return float(np.sqrt(np.mean(floor_j**2)))


def noise_spread(floors: np.ndarray) -> float:
    """How far noise alone moves the squared gap: the range of the squared overall gaps of
    :func:`noise_floors`' draws. Small where replays are smooth (an arm: a tenth of the squared
    floor); where impacts or stamping feet make windows diverge with the noise, larger than
    the squared floor itself."""
    squares = np.mean(floors**2, axis=1)
    return float(squares.max() - squares.min())


def bootstrap_interval(fitter: Fitter, candidate: Candidate, draws: int, seed: int, sandwich_sd: np.ndarray,
                       max_iter: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """95 % intervals by parametric bootstrap: refit ``candidate`` on ``draws`` sets of
    ``fitter``'s training logs it resynthesises itself (:func:`resynthesize`), each refit with
    ``fitter``'s settings (:meth:`Fitter.on`). The refits' mean offset
    is a bias of replay fits (noisy initial states and velocities), which the sandwich
    covariance ignores; their spread, a second estimate of the random error beside
    ``sandwich_sd``. The resynthesised noise only approximates the real one (white, not
    quantised), so the offset sizes the bias without correcting it: the interval is
    centred on the estimate, half-width t x sqrt(max(spread, sandwich_sd)^2 + offset^2).
    Refits start at the estimate, so a few iterations (``max_iter``) reach their optimum."""
    rep = fitter.rep
    refits = []
    for b in range(draws):
        trajs = resynthesize(rep, candidate.combo, candidate.x, np.random.default_rng(seed + 1 + b))
        combo = Combo(candidate.combo.effects, trajs[0])
        refits.append(fitter.on(Replayer(trajs, rep.windows, rep.nthread), max_iter).fit(combo, [candidate.x]).x)
    refits = np.array(refits)
    spread, offset = refits.std(axis=0, ddof=1), refits.mean(axis=0) - candidate.x
    half = stats.t.ppf(0.975, draws - 1) * np.sqrt(np.maximum(spread, sandwich_sd) ** 2 + offset**2)
    return candidate.x - half, candidate.x + half


@dataclass(frozen=True)
class Replay:
    """The held-out windows replayed before and after the selected (or closest) effect, for plots.

    Attributes:
        windows: the replay windows.
        dt: the logs' time step (s).
        mask: (W, S) bool, the steps each window has.
        target: (W, S, J) the logged joint positions.
        pred_before, pred_after: (W, S, J) the simulated ones, nominal and with the effect.
        sources: where each held-out log came from.
    """

    windows: Any
    dt: float
    mask: np.ndarray
    target: np.ndarray
    pred_before: np.ndarray
    pred_after: np.ndarray
    sources: list[str]


@dataclass(frozen=True)
class Diagnosis:
    """What :func:`diagnose` finds. :meth:`to_json` is ``report.json``; ``docs/sim2real.md``
    describes every field."""

    verdict: str
    joints: list[str]
    gap_before: float
    noise_floor: float
    noise_floor_best: float
    noise_sigma: dict[str, float]
    where: dict[str, Any]
    ranking: list[dict[str, Any]]
    skipped: list[dict[str, str]]
    heldout: str
    heldout_speed_ratio: float
    config: dict[str, Any]
    selected: dict[str, Any] | None
    closest: dict[str, Any] | None
    gap_after_heldout: float
    residual: dict[str, Any] | None
    shrink: float
    shrink_above_floor: float
    rollouts: int
    seconds: float
    mujoco_warnings: dict[str, int]
    replay: Replay = field(repr=False)

    def to_json(self) -> dict[str, Any]:
        """Every field but the replay arrays, in order."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "replay"}


def diagnose(train: list[tuple[RealLog, mujoco.MjModel | mujoco.MjSpec]],
             holdout: list[tuple[RealLog, mujoco.MjModel | mujoco.MjSpec]] | None = None,
             config: DiagnoseConfig | None = None) -> Diagnosis:
    """Diagnose the sim-to-real gap of ``train`` logs (each with the model it ran on). Given as
    an ``MjSpec``, the model can also be extended by the effects that add parts to it (a gear's
    rotor); given compiled, those effects are skipped."""
    with collected_warnings() as warnings:
        return _diagnose(train, holdout, config or DiagnoseConfig(), warnings)


def _diagnose(train: list[tuple[RealLog, mujoco.MjModel | mujoco.MjSpec]],
              holdout: list[tuple[RealLog, mujoco.MjModel | mujoco.MjSpec]] | None, cfg: DiagnoseConfig,
              warnings: Counter[str]) -> Diagnosis:
    t_start = time.perf_counter()
    if not train:
        raise ValueError("diagnose needs at least one log")
    split = holdout is None or not holdout
    if split:
        train, holdout = _split(train, cfg.holdout_fraction, cfg.holdout_blocks)
    tr_train = [bind(log, model) for log, model in train]
    tr_test = [bind(log, model) for log, model in holdout]
    rep_train = Replayer(tr_train, make_windows(tr_train, cfg.window_s), cfg.nthread)
    rep_test = Replayer(tr_test, make_windows(tr_test, cfg.window_s), cfg.nthread)
    names = tr_train[0].log.joint_names

    r0_test = residuals(rep_test, [nominal_inputs(tr_test)])[0]
    r0_train = residuals(rep_train, [nominal_inputs(tr_train)])[0]
    gap_before = gap_rms(r0_test, rep_test.mask)
    floor_draws = noise_floors(rep_test, cfg.seed, draws=cfg.floor_draws)
    floor_j = median_draw(floor_draws)
    floor = _overall(floor_j)

    rep_all = Replayer(tr_train + tr_test, _concat_windows(rep_train, rep_test), cfg.nthread)
    r0_all = np.concatenate([r0_train, r0_test])
    where_before = where(rep_all, r0_all, rep_all.open_loop(nominal_inputs(rep_all.trajs)), floor_j)
    train_rms = np.sqrt(np.sum(r0_train**2, axis=(0, 1)) / rep_train.mask.sum())
    focus = names[int(np.argmax(train_rms**2 - floor_j**2))]

    fitter = Fitter(rep_train, cfg.max_iter, solver=cfg.solver, step_fraction=cfg.step_fraction,
                    robust_scale=cfg.robust_scale * floor or None,
                    window_scale=noise_weights(rep_train, cfg.seed, cfg.floor_draws) if cfg.noise_weights else None)
    effects = library(tr_train[0], focus=focus if len(names) > 1 else None, families=cfg.families or None)
    candidates: list[Candidate] = []
    skipped: list[dict[str, str]] = []
    for effect in tqdm([e for e in effects if e.refines is None], desc="fit effects", disable=not cfg.show_progress,
                       leave=False):
        try:
            candidates.append(_fit(fitter, Combo((effect,), tr_train[0])))
        except CannotApply as err:  # one candidate that cannot act on this log ends nothing else
            skipped.append({"effect": effect.label, "reason": str(err)})
    _evaluate(rep_test, candidates)
    refined = _refinements([e for e in effects if e.refines is not None], candidates, tr_train[0], fitter, cfg,
                           skipped)
    _evaluate(rep_test, refined)
    candidates += refined
    combined = _forward_pairs(candidates, tr_train[0], fitter, rep_test, cfg, floor_j, focus)
    mixture = _per_joint_mixture(candidates, tr_train[0], fitter) if len(names) > 1 else None
    combined += [mixture] if mixture is not None else []
    combined = _supported(combined, rep_train, cfg.tolerance * noise_spread(floor_draws), skipped)
    _evaluate(rep_test, combined)
    candidates += combined
    joint_model = _joint_model_fit(tr_train, fitter, cfg, skipped) if cfg.inverse_dynamics else None
    if joint_model is not None:
        candidates.append(_pruned(joint_model, fitter, rep_test, floor, cfg))  # evaluated there
    for c in candidates:
        c.score = c.heldout_gap**2 * (1 + cfg.penalty * c.nparam)
    ranked = sorted(candidates, key=lambda c: c.score)

    # The floor of the best-scoring candidate itself: where its dynamics have sharper events
    # than the nominal model's (impacts, stick-slip), even the exact model replays less well.
    # "Explained" asks whether the gap is one the exact model can produce (its largest
    # draw). Gaps that differ by less than its typical floor (the median draw) do not tell
    # candidates apart: that sets the parsimony tolerance, and the simpler model inherits it.
    # (The largest draw there let one diverging window hand a close match's place to a
    # simpler candidate twice its gap.)
    best_floors = noise_floors(rep_test, cfg.seed, ranked[0], cfg.floor_draws)
    floor_best = _overall(best_floors[-1])
    floor_typical = max(floor, _overall(median_draw(best_floors)))
    ranked = _parsimonious_first(ranked, floor_typical, cfg.tolerance)
    alternatives = _indistinguishable(ranked, floor_typical, cfg.tolerance)
    verdict, selected = _verdict(ranked, gap_before, floor, floor_best, cfg)
    best = ranked[0]
    runner = next((c for c in ranked[1:] if c.combo.family != best.combo.family), None)
    chosen = selected or best
    half = fitter.confidence(chosen.combo, chosen.x)
    identified = np.isfinite(half)
    lo, hi = chosen.x - half, chosen.x + half
    ci_method = "sandwich covariance, clustered by window"
    if verdict == "explained" and cfg.bootstrap >= 3:
        lo, hi = bootstrap_interval(fitter, chosen, cfg.bootstrap, cfg.seed, half / 1.96)
        ci_method += f", widened by a parametric bootstrap ({cfg.bootstrap} refits)"
    # a parameter the data do not determine: any value in its range
    lo = np.where(identified, lo, [p.lo for p in chosen.combo.params])
    hi = np.where(identified, hi, [p.hi for p in chosen.combo.params])
    r_after = residuals(rep_test, [chosen.combo.inputs(chosen.x, tr_test)])[0]
    per_joint_after = np.sqrt(np.sum(r_after**2, axis=(0, 1)) / rep_test.mask.sum())
    summary = {
        "effect": chosen.combo.label, "family": chosen.combo.family,
        "parameters": [{"name": p.name, "value": float(v), "ci95": [float(a), float(b)], "unit": p.unit,
                        "effect": e.label, "at_bound": at_bound(p, float(v)), "identified": bool(ok)}
                       for (p, v, a, b, e, ok) in zip(chosen.combo.params, chosen.x, lo, hi, _owners(chosen.combo),
                                                      identified)],
        "ci_method": ci_method,
        "gap_train": chosen.train_gap, "gap_heldout": chosen.heldout_gap,
        "margin_over_runner_up": (None if runner is None else float(runner.score / chosen.score - 1.0)),
        "runner_up": None if runner is None else runner.combo.label,
        "per_joint_gap_after": {n: float(g) for n, g in zip(names, per_joint_after)},
        "shares": part_shares(chosen, rep_test),
        "indistinguishable": [{"effect": c.combo.label, "family": c.combo.family, "gap_heldout": c.heldout_gap}
                              for c in alternatives],
    }
    gap_after = chosen.heldout_gap if selected is not None else gap_before
    excess0 = gap_before**2 - floor**2
    target = rep_test.targets(nominal_inputs(tr_test))
    replay = Replay(windows=rep_test.windows, dt=tr_test[0].log.dt, mask=rep_test.mask, target=target,
                    pred_before=target + r0_test, pred_after=target + r_after,
                    sources=[t.log.meta.get("source", f"log{i}") for i, t in enumerate(tr_test)])
    return Diagnosis(
        verdict=verdict,
        joints=list(names),
        gap_before=gap_before,
        noise_floor=floor,
        noise_floor_best=floor_best,
        noise_sigma={n: float(s) for n, s in zip(names, tr_train[0].sigma)},
        where=where_before,
        ranking=[_row(c, gap_before, floor, names) for c in ranked],
        skipped=skipped,
        heldout=_heldout_label(cfg) if split else HELDOUT_LOGS,
        heldout_speed_ratio=speed_ratio([log for log, _ in train], [log for log, _ in holdout]),
        config={k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.__dict__.items()},
        selected=summary if selected is not None else None,
        closest=summary if selected is None else None,
        gap_after_heldout=gap_after,
        residual=residual_structure(rep_test, r_after, floor_j) if verdict == "unexplained" else None,
        shrink=1.0 - gap_after / gap_before if gap_before > 0 else 0.0,
        shrink_above_floor=(float(1 - max(gap_after**2 - floor**2, 0) / excess0) if excess0 > 0 else 0.0),
        rollouts=fitter.rollouts,
        seconds=time.perf_counter() - t_start,
        mujoco_warnings=dict(warnings),
        replay=replay,
    )


def _owners(combo: Combo) -> list[Effect]:
    return [e for e, n in zip(combo.effects, combo.sizes) for _ in range(n)]


def _concat_windows(a: Replayer, b: Replayer):
    wa, wb = a.windows, b.windows
    if wa.size != wb.size:
        raise ValueError("train and held-out windows must have the same length")
    return type(wa)(np.concatenate([wa.traj, wb.traj + len(a.trajs)]), np.concatenate([wa.start, wb.start]),
                    np.concatenate([wa.length, wb.length]), wa.pattern + wb.pattern, wa.size)


def at_bound(param: Param, value: float) -> bool:
    """Whether a fitted value sits at its bound (within 1 % of the range): the fit wanted more,
    so the effect is not the right one, or its range is too narrow."""
    return min(value - param.lo, param.hi - value) <= 0.01 * (param.hi - param.lo)


def _fit(fitter: Fitter, combo: Combo, starts: list[np.ndarray] | None = None) -> Candidate:
    res = fitter.fit(combo, starts)
    return Candidate(combo, res.x, res.train_gap)


def _evaluate(rep: Replayer, cands: list[Candidate]) -> None:
    """Held-out gap of each candidate, in batches that keep memory bounded."""
    batch = max(1, int(4e7 // max(1, len(rep.windows) * rep.nstep * (rep.trajs[0].model.nq * 2 + 1) * 8)))
    for i in range(0, len(cands), batch):
        chunk = cands[i:i + batch]
        r = residuals(rep, [c.combo.inputs(c.x, rep.trajs) for c in chunk])
        for c, rc in zip(chunk, r):
            c.heldout_gap = gap_rms(rc, rep.mask)
            c.heldout_per_joint = np.sqrt(np.sum(rc**2, axis=(0, 1)) / rep.mask.sum())


def _refinements(effects: list[Effect], singles: list[Candidate], ref: Trajectory, fitter: Fitter,
                 cfg: DiagnoseConfig, skipped: list[dict[str, str]]) -> list[Candidate]:
    """Fits of the effects that nest a simpler one (:attr:`Effect.refines`), each only where
    that simpler effect, in the same scope, is among the ``cfg.refine_top`` best singles
    (held-out gap), and from its fit: a richer form of an effect that does not help
    does not help either, and its fit costs many times the simpler one's. The others go to
    ``skipped`` with the reason."""
    ranked = sorted(singles, key=lambda c: c.heldout_gap)
    out = []
    for effect in effects:
        simple = next(((rank, c) for rank, c in enumerate(ranked) if c.combo.effects[0].name == effect.refines
                       and c.combo.effects[0].joints == effect.joints
                       and c.combo.effects[0].per_joint == effect.per_joint), None)
        if simple is None or simple[0] >= cfg.refine_top:
            where = "was not fitted" if simple is None else f"ranks {simple[0] + 1} of {len(ranked)}"
            skipped.append({"effect": effect.label,
                            "reason": f"not refined: its simpler form {effect.refines} {where}"})
            continue
        out.append(_fit(fitter, Combo((effect,), ref), effect.nested_starts(simple[1].x, ref)))
    return out


def _forward_pairs(singles: list[Candidate], ref: Trajectory, fitter: Fitter, rep_test: Replayer,
                   cfg: DiagnoseConfig, floor_j: np.ndarray, focus: str) -> list[Candidate]:
    """Forward selection's second step. Each of the ``cfg.bases`` best single effects (held-out
    gap, distinct families; and a richer form of one above them, :func:`forward_bases`) is a
    base, and every single effect of another family (for the bases after the best, the
    ``cfg.later_base_partners`` best ones) is fitted together with it for a few iterations, both
    from their single fits (the screen: per-joint effects' derivatives blockwise, so a screen
    costs about two single fits). The new effect no longer has to soak up the base, as it does
    when fitted alone, and the base gives back what it soaked up of the new one, as a base held
    at its fit cannot. So are the library's effects confined to the joint
    the base leaves worst, when that is not the joint the singles were confined to (a second
    effect on another joint). The ``cfg.pairs`` pairs whose screens leave the smallest held-out
    gaps are then fitted fully. More than one base, because an effect fitted alone may stand in
    for a relative of the true one (a sensor delay for an actuator delay beside friction)."""
    ranked = sorted(singles, key=lambda c: c.heldout_gap)
    bases = forward_bases(ranked, cfg.bases)
    names = ref.log.joint_names
    screen = fitter.on(fitter.rep, cfg.screen_iter, restarts=0, blockwise=True)
    screened: list[Candidate] = []
    seen: set[frozenset[str]] = set()
    for i, base in enumerate(bases):
        first = base.combo.effects[0]
        pool = ranked if i == 0 else ranked[:cfg.later_base_partners]
        partners: list[tuple[Effect, list[np.ndarray] | None]] = [(c.combo.effects[0], [c.x]) for c in pool]
        worst = names[int(np.argmax(base.heldout_per_joint**2 - floor_j**2))] if len(names) > 1 else focus
        if worst != focus:
            partners += [(e, None) for e in library(ref, focus=worst, families=cfg.families or None)
                         if e.joints == (worst,) and not e.per_joint and e.refines is None]
        for effect, start in partners:
            key = frozenset((base.combo.label, effect.label))
            if effect.family == base.combo.family or key in seen:
                continue
            seen.add(key)
            combo = Combo((first, effect), ref)
            try:
                res = screen.fit(combo, [np.concatenate([base.x, s]) for s in start or effect.starts(ref)])
            except CannotApply:
                continue
            screened.append(Candidate(combo, res.x, res.train_gap))
    fitter.rollouts += screen.rollouts
    _evaluate(rep_test, screened)
    out = []
    for k in np.argsort([c.heldout_gap for c in screened])[:cfg.pairs]:
        out.append(_fit(fitter, screened[k].combo, [screened[k].x]))
    return out


def forward_bases(ranked: list[Candidate], n: int) -> list[Candidate]:
    """Forward selection's bases among the single effects ``ranked`` (best first): the ``n`` best
    of distinct families, then every richer form of an effect (:attr:`Effect.refines`: gearbox
    friction of load friction) that ranks above the last of them. It shares its simpler form's
    family, so it is never a base by the first rule, and in the pairs of the simpler form's base
    the simpler form stands in for it."""
    bases: list[Candidate] = []
    for c in ranked:
        if len(bases) < n and all(c.combo.family != b.combo.family for b in bases):
            bases.append(c)
    if not bases:
        return bases
    last = next(k for k, c in enumerate(ranked) if c is bases[-1])
    return bases + [c for c in ranked[:last] if c.combo.effects[0].refines is not None
                    and all(c is not b for b in bases)]


def _per_joint_mixture(singles: list[Candidate], ref: Trajectory, fitter: Fitter) -> Candidate | None:
    """Per joint, the per-joint effect that leaves that joint's held-out gap smallest; those
    effects confined to their joints and fitted together, from their single fits (one
    parameter per joint, so the fit keeps its one-rollout diagonal Jacobian). ``None`` when one
    family wins every joint (the per-joint effect itself is already a candidate). A joint is
    won only by an effect with a parameter on it (actuator effects have none on unactuated
    joints)."""
    names = ref.log.joint_names
    scoped = [(c, c.combo.effects[0].columns(ref)) for c in singles if len(c.combo.effects) == 1
              and c.combo.effects[0].per_joint and c.combo.effects[0].joints is None]
    per_joint = [(c, cols) for c, cols in scoped if c.nparam == len(cols)]  # one parameter per joint
    if len(per_joint) < 2:
        return None
    gaps = np.full((len(per_joint), len(names)), np.inf)
    for k, (c, cols) in enumerate(per_joint):
        gaps[k, cols] = c.heldout_per_joint[cols]
    choice = np.where(np.isfinite(gaps.min(axis=0)), np.argmin(gaps, axis=0), -1)  # -1: no effect acts there
    winners = sorted(set(choice.tolist()) - {-1})
    if len(winners) < 2:
        return None
    effects, start = [], []
    for f in winners:
        winner, own = per_joint[f]
        cols = np.flatnonzero(choice == f)
        effects.append(type(winner.combo.effects[0])(joints=tuple(names[c] for c in cols), per_joint=True))
        start.append(winner.x[np.searchsorted(own, cols)])
    return _fit(fitter, Combo(tuple(effects), ref), [np.concatenate(start)])


def _joint_model_fit(trajs: list[Trajectory], fitter: Fitter, cfg: DiagnoseConfig,
                     skipped: list[dict[str, str]]) -> Candidate | None:
    """Every joint's Coulomb friction, damping, armature and load friction fitted together by
    replay, from the inverse-dynamics estimate (:func:`~crisp_gym.sim2real.inverse.joint_model_start`);
    ``None`` where the library is restricted to other families, or (with the reason in ``skipped``)
    where that estimate cannot be made."""
    effects = tuple(kind(per_joint=True) for kind in JOINT_MODEL)
    combo = Combo(effects, trajs[0])
    if cfg.families and not {e.family for e in effects} <= set(cfg.families):
        return None  # a library restricted to other families, as the singles are
    try:
        return _fit_per_joint(fitter, combo, joint_model_start(trajs, effects), cfg.screen_iter)
    except CannotApply as err:
        skipped.append({"effect": combo.label, "reason": str(err)})
        return None


def _fit_per_joint(fitter: Fitter, combo: Combo, start: np.ndarray, polish_iter: int) -> Candidate:
    """Fit several per-joint effects together: Levenberg-Marquardt with each effect's derivatives
    from one perturbed rollout (cross-joint terms dropped: 4 rollouts a Jacobian for the joint
    model, not 4 per joint), then ``polish_iter`` iterations with every parameter's own, for what
    couples the joints (a trunk on a rail, contacts). Rollouts count on ``fitter``."""
    rough = fitter.on(fitter.rep, fitter.max_iter, blockwise=True)
    polish = fitter.on(fitter.rep, polish_iter, blockwise=False)
    candidate = _fit(polish, combo, [rough.fit(combo, [start]).x])
    fitter.rollouts += rough.rollouts + polish.rollouts
    return candidate


def _pruned(candidate: Candidate, fitter: Fitter, rep_test: Replayer, floor: float, cfg: DiagnoseConfig) -> Candidate:
    """Backward elimination by the parsimony rule (:func:`_parsimonious_first`): while leaving one
    effect out (the others at their fit) raises the squared held-out gap by less than
    ``cfg.tolerance`` x the squared ``floor``, leave out the one whose absence raises it least and
    refit the rest. A joint model fitted where only two of its effects act keeps those two, and
    is named by them."""
    _evaluate(rep_test, [candidate])
    current = candidate
    while len(current.combo.effects) > 1:
        parts = current.combo.split(current.x)
        trials = [Candidate(Combo(current.combo.effects[:k] + current.combo.effects[k + 1:], current.combo.ref),
                            np.concatenate(parts[:k] + parts[k + 1:]), float("nan"))
                  for k in range(len(parts))]
        _evaluate(rep_test, trials)
        best = min(trials, key=lambda c: c.heldout_gap)
        if best.heldout_gap**2 - current.heldout_gap**2 >= cfg.tolerance * floor**2:
            break
        current = _fit_per_joint(fitter, best.combo, best.x, cfg.screen_iter)
        _evaluate(rep_test, [current])
    return current


def gaps_without_each_part(candidate: Candidate, rep: Replayer) -> tuple[float, list[float]]:
    """The gap of a combined candidate on ``rep``'s windows, and its gap with each part left
    out in turn (the others held at their fit)."""
    effects, parts = candidate.combo.effects, candidate.combo.split(candidate.x)
    ref = rep.trajs[0]
    combos = [Combo(tuple(Frozen(e, xe) for j, (e, xe) in enumerate(zip(effects, parts)) if j != i), ref)
              for i in range(-1, len(effects))]  # -1: every part
    r = residuals(rep, [c.inputs(np.zeros(0), rep.trajs) for c in combos])
    gaps = [gap_rms(ri, rep.mask) for ri in r]
    return gaps[0], gaps[1:]


def _supported(combined: list[Candidate], rep_train: Replayer, threshold: float,
               skipped: list[dict[str, str]]) -> list[Candidate]:
    """The combinations whose every part earns its place on the windows it was fitted on:
    leaving it out (the others at their fit) raises the squared training gap by at least
    ``threshold`` (the tolerance x :func:`noise_spread`: more than noise alone moves it). A part
    that does less is not seen in the data it was fitted to, and what it seems to add held out
    is chance: where replays have impacts or stamping feet, any small change makes some windows
    diverge differently (a gear play's pair with a ground 0.1 mm lower halved its held-out gap).
    The others go to ``skipped``, with the idle parts."""
    kept = []
    for c in combined:
        gap, without = gaps_without_each_part(c, rep_train)
        idle = [e.label for e, g in zip(c.combo.effects, without) if g**2 - gap**2 < threshold]
        if idle:
            skipped.append({"effect": c.combo.label, "reason": f"{' and '.join(idle)} does not earn its place: left "
                            "out, the training gap rises less than noise alone moves it"})
        else:
            kept.append(c)
    return kept


def part_shares(candidate: Candidate, rep: Replayer) -> list[dict[str, Any]]:
    """Each part of a combined candidate, with its share of what the combination removes from the
    squared held-out gap: the gap comes back by ``gap_without² - gap²`` when that part alone is
    left out (the others held at their fit); shares are those rises, normalised."""
    effects = candidate.combo.effects
    if len(effects) < 2:
        return []
    gap, without = gaps_without_each_part(candidate, rep)
    rise = np.maximum(np.array(without) ** 2 - gap**2, 0.0)
    shares = rise / rise.sum() if rise.sum() > 0 else np.full(len(rise), 1.0 / len(rise))
    return [{"effect": e.label, "share": float(sh), "gap_without": float(g)}
            for e, sh, g in zip(effects, shares, without)]


def _simpler(a: Candidate, b: Candidate) -> bool:
    """Whether ``a`` is the simpler model: fewer parameters, or as many in fewer effects (one
    effect on every joint rather than a per-joint mixture of four)."""
    return (a.nparam, len(a.combo.effects)) < (b.nparam, len(b.combo.effects))


def _parsimonious_first(ranked: list[Candidate], floor: float, tolerance: float) -> list[Candidate]:
    """Move the simplest candidate (:func:`_simpler`) indistinguishable from the best (at the
    noise level) to the front."""
    best = ranked[0]
    while True:
        simpler = [c for c in ranked if _simpler(c, best)
                   and c.heldout_gap**2 <= best.heldout_gap**2 + tolerance * floor**2]
        if not simpler:
            break
        best = min(simpler, key=lambda c: c.score)
    return [best] + [c for c in ranked if c is not best]


def _indistinguishable(ranked: list[Candidate], floor: float, tolerance: float) -> list[Candidate]:
    """Candidates of other families that these logs cannot tell from the winner ``ranked[0]``:
    squared held-out gaps within ``tolerance`` x ``floor``² of the smallest, as for parsimony.
    The simplest of each such family, simplest first; a candidate holding every family of the
    winner or of one listed before (the same model with a part it does not need) is left out."""
    limit = min(c.heldout_gap for c in ranked) ** 2 + tolerance * floor**2
    listed = [set(ranked[0].combo.family.split("+"))]
    out = []
    for c in sorted(ranked[1:], key=lambda c: (c.nparam, c.score)):
        families = set(c.combo.family.split("+"))
        if c.heldout_gap**2 <= limit and not any(families >= seen for seen in listed):
            out.append(c)
            listed.append(families)
    return out


def _verdict(ranked: list[Candidate], gap_before: float, floor: float, floor_best: float,
             cfg: DiagnoseConfig) -> tuple[str, Candidate | None]:
    """"none" when the nominal model's gap is at its floor; "explained" when the best
    candidate's gap is near the floor of a model that is exactly right (the nominal's, or
    the candidate's own if higher); else "unexplained"."""
    if gap_before <= cfg.none_factor * floor:
        return "none", None
    best = ranked[0]
    if best.heldout_gap <= cfg.explained_factor * max(floor, floor_best) and best.heldout_gap < gap_before:
        return "explained", best
    return "unexplained", None


def _named_values(c: Candidate) -> dict[str, float]:
    """Parameter values by name; where two effects of a combination name a parameter alike
    (every per-joint effect has ``added@<joint>``), by ``<effect name>.<parameter name>``."""
    names = [p.name for p in c.combo.params]
    owners = _owners(c.combo)
    return {(f"{e.name}.{n}" if names.count(n) > 1 else n): float(v) for n, e, v in zip(names, owners, c.x)}


def _row(c: Candidate, gap_before: float, floor: float, names: tuple[str, ...]) -> dict:
    return {"effect": c.combo.label, "family": c.combo.family, "nparam": c.nparam,
            "parameters": _named_values(c),
            "gap_train": c.train_gap, "gap_heldout": c.heldout_gap, "score": c.score,
            "gap_heldout_per_joint": {n: float(g) for n, g in zip(names, c.heldout_per_joint)},
            "shrink": 1.0 - c.heldout_gap / gap_before if gap_before > 0 else 0.0,
            "gap_over_floor": c.heldout_gap / floor if floor > 0 else float("inf")}
