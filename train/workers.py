"""Collection in worker processes on this machine (``TrainConfig.collector_workers``).

In one process a collection step runs MuJoCo on every core, then the policy, the env's
observations and TorchRL's bookkeeping on one while the others wait: on two cores collection
kept 1.5 of them busy. With ``collector_workers = W``, TorchRL's ``MultiSyncCollector``
splits the ``num_envs`` simulations between W processes, each stepping its share with one
MuJoCo thread and running the policy on one torch thread, so every core works all through
collection; the trainer waits meanwhile and then updates on ``torch_threads`` (the iteration,
the batch and its layout are those of one process).

Each worker's env draws its starts from its own adaptive sampler (so a run stays reproducible
from its seed), whose counts live in a memory-mapped file: :class:`SharedStartCounts` lets the
trainer log them and save and restore them with its checkpoints as it does in one process.
(TorchRL hands a worker its env function by value, so a shared tensor inside it would arrive
as a copy; a file's path arrives as itself.)
"""

from __future__ import annotations

import contextlib
import signal
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from crisp_gym.envs.start_sampler import StartSampler
from crisp_gym.train.config import TrainConfig


def counts_table(path: str | Path, size: int, create: bool = False) -> np.ndarray:
    """The start counts kept in the file at ``path``: a float64 array of ``size`` mapped onto it;
    ``create`` makes the file, zero-filled."""
    return np.memmap(path, dtype=np.float64, mode="w+" if create else "r+", shape=(size,))


class SharedStartCounts:
    """The adaptive start counts of every worker's env, in files mapped into memory, seen through
    the trainer's sampler. A context manager: leaving it deletes the files.

    Args:
        sampler: the trainer's own sampler (of an env that is never stepped); after
            :meth:`gather` its counts are the sum of the workers', the counts one process
            stepping every simulation would have kept.
        workers: how many workers.
    """

    def __init__(self, sampler: StartSampler, workers: int):
        self.total = np.zeros(sampler.counts_size)
        sampler.attach(self.total)
        self._directory = tempfile.TemporaryDirectory(prefix="crisp-start-counts-")
        self.paths = [Path(self._directory.name) / f"worker{k}.f64" for k in range(workers)]
        self.tables = [counts_table(path, sampler.counts_size, create=True) for path in self.paths]

    def gather(self) -> None:
        """Sum the workers' counts into the trainer's sampler (call while the workers are idle)."""
        self.total[:] = np.sum(self.tables, axis=0)

    def scatter(self) -> None:
        """Give every worker an equal share of the trainer's counts (a resumed run's, before collecting)."""
        for table in self.tables:
            table[:] = self.total / len(self.tables)

    def close(self) -> None:
        """Delete the files (the trainer's sampler keeps the last gathered counts)."""
        self.tables = []
        self._directory.cleanup()

    def __enter__(self) -> SharedStartCounts:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def worker_config(cfg: TrainConfig) -> TrainConfig:
    """The config of one worker's env: its share of the simulations, stepped in its own process on
    one MuJoCo thread."""
    return replace(cfg, num_envs=cfg.num_envs // cfg.worker_processes, num_threads=1, collector_workers=0)


STOP_SIGNALS = frozenset({signal.SIGINT, signal.SIGTERM})
"""What stops a run: a terminal's Ctrl-C, and a scheduler's or session's end."""


def ignore_stop_signals() -> None:
    """Run first in every worker: ignore SIGINT and SIGTERM, then let them through (they were held
    from the worker's birth, :func:`stop_signals_held`; one held meanwhile is dropped). A terminal's
    Ctrl-C reaches every process of its group, and a worker that died of it left the trainer
    waiting for its reply forever, where the trainer should save its checkpoint and then stop the
    workers itself."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


@contextlib.contextmanager
def stop_signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back from this thread inside the block, and from the processes it
    starts until they let them through themselves. A spawned worker spends seconds importing
    before :func:`ignore_stop_signals` runs; a Ctrl-C then killed it and the trainer waited for it
    forever. A signal held in this thread arrives when the block ends."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def worker_env(env_fn: Callable[[TrainConfig, int], Any], cfg: TrainConfig, seed: int, counts: Path) -> Any:
    """A worker's TorchRL env (run in the worker): ``env_fn(cfg, seed)``, its sampler's counts kept
    in the file ``counts``."""
    env = env_fn(cfg, seed)
    sampler = env.vec_env.start_sampler
    sampler.attach(counts_table(counts, sampler.counts_size))
    return env


def worker_collector(cfg: TrainConfig, env_fn: Callable[[TrainConfig, int], Any], policy: Any,
                     counts: SharedStartCounts, seed: int) -> Any:
    """TorchRL's ``MultiSyncCollector`` over ``cfg.worker_processes`` workers, the envs seeded
    ``seed + k``, each batch stacked as (workers, envs per worker, steps). ``env_fn`` must be
    picklable (a module-level function): the workers are spawned processes."""
    from torchrl.collectors import MultiSyncCollector  # noqa: PLC0415

    local = worker_config(cfg)
    with stop_signals_held():  # the workers are born with them held (a mask survives fork and exec)
        collector = MultiSyncCollector(
            [partial(worker_env, env_fn, local, seed + k, path) for k, path in enumerate(counts.paths)],
            policy, frames_per_batch=cfg.frames_per_iteration, total_frames=-1, env_device="cpu",
            policy_device="cpu", storing_device="cpu", cat_results="stack", num_sub_threads=1,
            init_fn=ignore_stop_signals,
            num_threads=torch.get_num_threads())  # its default: the trainer's threads cut to the CPUs minus the workers
    collector.set_seed(seed)  # the workers' torch generators, which sample the actions
    collector.update_policy_weights_()
    return collector
