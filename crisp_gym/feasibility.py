"""Can the humanoid follow a reference at all? A sampling search for actions that track it.

When every policy stalls at the same frames of a clip, either the reference asks for something
the simulated body cannot do there (a floating foot under load, a push no sole can give) or the
moves are possible and a policy has not learned them. This module tells the two apart: a beam
search in the spirit of sampling-based motion control (SAMCON) looks for *open-loop* actions that
keep every body within ``termination_distance`` of its reference from a start frame to the end.

One search round: each of ``elites`` states carried so far branches into ``population /
elites`` copies in the batched env (:meth:`~crisp_gym.envs.track_vector.CrispTrackVectorEnv.restore`);
each copy acts for ``chunk`` control steps with the proposal (zero, i.e. the PD reference, or a
policy's mean action) plus one Gaussian offset per copy and round; the copies whose episode did
not end, ranked by their summed largest body error, give the next elites. When no copy survives a
round the search goes back one to three rounds (further at each retry) and draws again; it gives
up after ``retries`` failed rounds without passing the furthest frame reached.

A found trajectory proves the clip is feasible for this humanoid from that start (the actions
replay in the env: ``tests/test_feasibility.py``); a failed search proves nothing, but the frame
where searches keep dying is where to look at the reference first.

``crisp feasibility CLIP [--policy POLICY] [-o DIR]`` runs one search and compares it with the PD
reference alone (zero actions) from the same start; ``DIR`` gets ``search.npz`` (the actions,
poses and errors, :meth:`SearchResult.save`) and ``search.png`` (both errors over the clip).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro
from tqdm.auto import tqdm

from crisp_gym.envs.library import ClipSource
from crisp_gym.envs.track import make_config
from crisp_gym.envs.track_vector import CrispTrackVectorEnv, EnvSnapshot

Proposal = Callable[[dict[str, np.ndarray]], np.ndarray]
"""Observations of the batch → (N, 69) mean actions around which the search draws."""


@dataclass(frozen=True)
class SearchConfig:
    """Knobs of the search (search_clip). The defaults found whole trajectories of flat_walk and
    of the captured cmu_131_01 from frame 0 (docs/training.md); smaller populations stall earlier.

    Attributes:
        population: simulations stepped per round (the batch size).
        elites: states carried from one round to the next.
        chunk: control steps per round (the open-loop horizon a branch is judged over).
        sigma: standard deviation of the action offsets (action units: radians of PD target).
        retries: failed rounds allowed without passing the furthest frame reached.
        seed: seeds the env and the offsets; a search is reproducible from it.
        num_threads: MuJoCo threads stepping the population (0: all CPUs).
    """

    population: int = 1024
    elites: int = 64
    chunk: int = 4
    sigma: float = 0.5
    retries: int = 30
    seed: int = 0
    num_threads: int = 0

    def __post_init__(self) -> None:
        if not 1 <= self.elites <= self.population:
            raise ValueError(f"elites must be in [1, population={self.population}], got {self.elites}")
        if self.chunk < 1 or self.retries < 0 or not self.sigma >= 0:
            raise ValueError(f"chunk must be at least 1, retries and sigma non-negative; got chunk={self.chunk}, "
                             f"retries={self.retries}, sigma={self.sigma}")


@dataclass
class SearchResult:
    """The best trajectory a search found.

    Attributes:
        clip: the clip's name.
        start_frame: where it started (from the reference's state there).
        reached: the last frame of the trajectory; ``num_frames - 1`` when ``whole``.
        whole: it tracked to the clip's end.
        actions: (T, 69) the actions of frames ``start_frame + 1 .. reached`` (the env's action units).
        qpos: (T, nq) the simulated pose after each action.
        max_body_error: (T,) the largest body distance from the reference after each action (m).
        seconds: wall time of the search.
        rounds: search rounds run, retries included.
        config: the search's settings.
        env_options: the ``CrispTrack-v0`` keywords it searched under (the actions replay with them).
    """

    clip: str
    start_frame: int
    reached: int
    whole: bool
    actions: np.ndarray
    qpos: np.ndarray
    max_body_error: np.ndarray
    seconds: float
    rounds: int
    config: SearchConfig = field(default_factory=SearchConfig)
    env_options: dict[str, bool | float | int | str] = field(default_factory=dict)

    def save(self, path: str | Path) -> Path:
        """Write the result as ``.npz`` (arrays plus the scalars and the search config)."""
        path = Path(path)
        np.savez_compressed(path, clip=self.clip, start_frame=self.start_frame, reached=self.reached,
                            whole=self.whole, actions=self.actions, qpos=self.qpos,
                            max_body_error=self.max_body_error, seconds=self.seconds, rounds=self.rounds,
                            **{f"config_{k}": v for k, v in vars(self.config).items()},
                            **{f"env_{k}": v for k, v in self.env_options.items()})
        return path


@dataclass
class _Round:
    """What a kept round contributes to the elites' lineages."""

    parents: np.ndarray  # (K,) each elite's parent among the previous round's elites
    actions: np.ndarray  # (H, K, 69)
    qpos: np.ndarray  # (H, K, nq)
    error: np.ndarray  # (H, K)


@dataclass
class _Beam:
    """The elites at a round boundary: their states and the rounds behind them."""

    frame: int
    state: EnvSnapshot
    rounds: int  # how many kept rounds lead here


def search_env(clip: ClipSource, num_envs: int, num_threads: int = 0, **env_options) -> CrispTrackVectorEnv:
    """The batched env a search steps (and its actions replay in): ``CrispTrack-v0`` with
    ``env_options``, whose simulations keep their last state when their episode ends."""
    return CrispTrackVectorEnv(num_envs=num_envs, clip=clip, num_threads=num_threads, autoreset_mode="next_step",
                               **env_options)


def search_clip(clip: ClipSource, start_frame: int = 0, config: SearchConfig = SearchConfig(),
                proposal: Proposal | None = None, on_round: Callable[[int, int], None] | None = None,
                **env_options) -> SearchResult:
    """Search for actions that track ``clip`` from ``start_frame`` to its end.

    Args:
        clip: one clip (a name, directory or loaded clip).
        start_frame: the reference frame the search starts from.
        config: the search's knobs.
        proposal: mean actions from observations (e.g. a policy's); ``None``: zero, the PD reference.
        on_round: called after every round with the frames passed so far (the furthest frame
            reached minus ``start_frame``) and the frames to the clip's end (progress bars).
        env_options: ``CrispTrack-v0`` keywords (e.g. ``velocity_feedforward=True``): the control
            law searched under; replay the actions in :func:`search_env` with the same ones.
    """
    env = search_env(clip, config.population, config.num_threads, **env_options)
    try:
        result = _search(env, start_frame, config, proposal, on_round)
    finally:
        env.close()
    result.env_options = dict(env_options)
    return result


def _search(env: CrispTrackVectorEnv, start_frame: int, config: SearchConfig, proposal: Proposal | None,
            on_round: Callable[[int, int], None] | None) -> SearchResult:
    if env.task.library.num_clips != 1:
        raise ValueError(f"a search tracks one clip, got the library {env.task.clip_names}")
    clip_index = 0
    last = int(env.task.num_frames[clip_index]) - 1
    rng = np.random.default_rng(config.seed)
    env.reset(seed=config.seed, options={"start_frame": start_frame, "clip": clip_index})
    beam = _Beam(start_frame, env.snapshot(np.array([0])), 0)
    saved = {start_frame: beam}
    kept: list[_Round] = []
    frontier, retries, rounds = start_frame, 0, 0
    started = time.perf_counter()
    while beam.frame < last:
        rounds += 1
        steps = min(config.chunk, last - beam.frame)
        parents = np.arange(config.population) % len(beam.state)
        current = env.restore(beam.state, parents)
        offsets = rng.normal(0.0, config.sigma, (config.population, env.single_action_space.shape[0]))
        offsets[: len(beam.state)] = 0.0  # every elite's own continuation is a candidate
        alive = np.ones(config.population, dtype=bool)
        cost = np.zeros(config.population)
        actions = np.empty((steps, *offsets.shape), dtype=np.float32)
        qpos = np.empty((steps, config.population, env.model.nq))
        error = np.empty((steps, config.population))
        for h in range(steps):
            mean = 0.0 if proposal is None else proposal(current)
            actions[h] = np.clip(mean + offsets, -1.0, 1.0)
            current, _, terminated, _, info = env.step(actions[h])
            qpos[h] = env.snapshot().physics["qpos"]
            error[h] = info["max_body_error"]
            alive &= ~terminated
            cost += error[h]
        survivors = np.flatnonzero(alive)
        if len(survivors) == 0:
            retries += 1
            if retries > config.retries:
                break
            back = beam.frame - config.chunk * min(retries, 3)
            beam = saved[max(f for f in saved if f <= max(back, start_frame))]
            saved = {f: b for f, b in saved.items() if f <= beam.frame}
            del kept[beam.rounds:]
            continue
        elites = survivors[np.argsort(cost[survivors], kind="stable")][: config.elites]
        kept.append(_Round(parents[elites], actions[:, elites], qpos[:, elites], error[:, elites]))
        beam = _Beam(beam.frame + steps, env.snapshot(elites), len(kept))
        saved[beam.frame] = beam
        if beam.frame > frontier:
            frontier, retries = beam.frame, 0
        if on_round is not None:
            on_round(frontier - start_frame, last - start_frame)
    return _best_lineage(env, clip_index, start_frame, kept, config, time.perf_counter() - started, rounds, last)


def _best_lineage(env: CrispTrackVectorEnv, clip: int, start_frame: int, kept: list[_Round],
                  config: SearchConfig, seconds: float, rounds: int, last: int) -> SearchResult:
    """The trajectory of the best elite of the last kept round, traced back through its parents."""
    nu, nq = env.single_action_space.shape[0], env.model.nq
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    elite = 0
    for kept_round in reversed(kept):
        parts.append((kept_round.actions[:, elite], kept_round.qpos[:, elite], kept_round.error[:, elite]))
        elite = int(kept_round.parents[elite])
    parts.reverse()
    actions = np.concatenate([p[0] for p in parts]) if parts else np.empty((0, nu), np.float32)
    qpos = np.concatenate([p[1] for p in parts]) if parts else np.empty((0, nq))
    error = np.concatenate([p[2] for p in parts]) if parts else np.empty(0)
    reached = start_frame + len(actions)
    return SearchResult(env.task.clip_names[clip], start_frame, reached, reached == last, actions, qpos, error,
                        seconds, rounds, config)


def pd_reference_errors(clip: ClipSource, start_frame: int = 0, **env_options) -> np.ndarray:
    """The largest body error after each step of the PD reference alone (zero actions) from
    ``start_frame``, up to the step that ends its episode."""
    env = search_env(clip, 1, 1, **env_options)
    try:
        env.reset(seed=0, options={"start_frame": start_frame})
        errors = []
        while True:
            _, _, terminated, truncated, info = env.step(np.zeros((1, env.single_action_space.shape[0])))
            errors.append(float(info["max_body_error"][0]))
            if terminated[0] or truncated[0]:
                return np.array(errors)
    finally:
        env.close()


def plot_search(result: SearchResult, pd_errors: np.ndarray, termination_distance: float, path: Path) -> None:
    """The found trajectory's and the PD reference's largest body error over the clip."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from crisp_gym.atomic import save_figure

    fig, ax = plt.subplots(figsize=(8, 3.5))
    frames = result.start_frame + 1 + np.arange(len(result.max_body_error))
    ax.plot(frames, result.max_body_error, label=f"search ({'whole clip' if result.whole else 'furthest found'})")
    ax.plot(result.start_frame + 1 + np.arange(len(pd_errors)), pd_errors, label="PD reference alone")
    ax.axhline(termination_distance, color="r", linestyle="--", label="early termination")
    ax.set_xlabel("frame")
    ax.set_ylabel("largest body error (m)")
    ax.set_title(f"{result.clip}: open-loop search from frame {result.start_frame}")
    ax.legend()
    save_figure(fig, path)


@dataclass(frozen=True)
class FeasibilityArgs:
    """Search for actions that track a clip, to tell an infeasible reference from an unlearnt one."""

    clip: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="CLIP")]
    """Clip name or directory."""
    start_frame: int = 0
    """The reference frame the search starts from."""
    policy: Path | None = None
    """Draw around this policy's mean actions (a run, checkpoint or policy file; its env options,
    e.g. the velocity feedforward, are used) instead of around the PD reference."""
    velocity_feedforward: bool = False
    """Without --policy: search under the env's velocity feedforward (see `crisp train --help`)."""
    search: SearchConfig = SearchConfig()
    output: Annotated[Path | None, tyro.conf.arg(aliases=["-o"])] = None
    """Directory for search.npz and search.png (created; existing files are replaced)."""


def _policy_proposal(path: Path) -> tuple[Proposal, dict[str, bool]]:
    """A policy's mean action as the proposal, and the env options it was trained with."""
    import torch

    from crisp_gym.policy.files import load_actor

    loaded = load_actor(path)

    def proposal(obs: dict[str, np.ndarray]) -> np.ndarray:
        with torch.no_grad():
            points = torch.as_tensor(obs["points"]) if loaded.scene_aware else None
            return loaded.actor(torch.as_tensor(obs["proprio"]), torch.as_tensor(obs["targets"]), points)[0].numpy()

    return proposal, {"scene_aware": loaded.scene_aware, "velocity_feedforward": loaded.velocity_feedforward}


def main(argv: list[str] | None = None) -> int:
    """``crisp feasibility`` (user errors are reported by :mod:`crisp_gym.cli`)."""
    args = tyro.cli(FeasibilityArgs, args=argv, prog="crisp feasibility")
    proposal, options = None, {"velocity_feedforward": args.velocity_feedforward}
    if args.policy is not None:
        proposal, options = _policy_proposal(args.policy)
    pd_errors = pd_reference_errors(args.clip, args.start_frame, **options)
    with tqdm(desc="search", unit="frame") as bar:
        def on_round(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        result = search_clip(args.clip, args.start_frame, args.search, proposal, on_round, **options)
    limit = make_config(None, options).termination_distance
    pd_reached = args.start_frame + int(np.sum(pd_errors <= limit))  # its episode ends at the first error past it
    if result.whole:
        verdict = (f"tracked to its end (frame {result.reached}) within the termination distance, largest body "
                   f"error {result.max_body_error.max():.3f} m: feasible for this humanoid from frame "
                   f"{result.start_frame}")
    else:
        verdict = (f"no trajectory past frame {result.reached} found (a failed search proves nothing; where "
                   f"searches keep dying is where to look at the reference)")
    print(f"{result.clip} from frame {result.start_frame}: {verdict}; {result.rounds} rounds, {result.seconds:.0f} s.\n"
          f"The PD reference alone: to frame {pd_reached}.")
    if args.output is not None:
        args.output.mkdir(parents=True, exist_ok=True)
        result.save(args.output / "search.npz")
        plot_search(result, pd_errors, limit, args.output / "search.png")
        print(f"wrote {args.output / 'search.npz'} and {args.output / 'search.png'}")
    return 0
