"""Where episodes start: reference state init over the clips of a motion library.

Every start draws a clip, then a frame of it. The clip:

* ``clip_sampling="fixed"``: with probabilities from ``clip_weights`` (equal by default);
* ``"adaptive"``: a mixture of those probabilities (share ``adaptive_uniform_share``) and
  each clip's weight times its recent failure rate (the share of its ended episodes that
  failed, forgotten as the frame bins' counts are): a library's hardest clips get the
  episodes where a fixed draw would spend them on clips already tracked.

The frame: frame 0 with ``rsi_first_frame_prob``, otherwise

* ``"uniform"``: any frame but the last, equally likely (the paper's reference state init);
* ``"adaptive"``: a time bin of ``adaptive_bin_seconds`` drawn in proportion to the recent
  failures in it and in the next ``adaptive_lookback`` bins, mixed with the uniform draw
  (share ``adaptive_uniform_share``), then a frame of that bin uniformly. Starting a little
  before where episodes fail gives the policy the approach as well as the hard part (the
  scheme BeyondMimic uses). Failures are counted where the episode terminated, with
  exponential forgetting over ``adaptive_memory`` ended episodes, so the distribution follows
  what the policy currently fails at.

The sampler holds counts, not a random generator: the env passes its own, which keeps runs
reproducible from the env's seed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from crisp_gym.envs.config import TrackConfig


class StartSampler:
    """Draws (clip, start frame) pairs; in adaptive mode, learns from ended episodes.

    Args:
        num_frames: frames of each clip at the control rate (each at least 2).
        config: ``start_sampling``, ``clip_sampling``, ``clip_weights``, ``rsi_first_frame_prob``,
            ``random_start`` and the ``adaptive_*`` fields.

    Attributes:
        fixed_clip_probabilities: (C,) the clip probabilities from ``clip_weights``.
        bin_edges: per clip, (B+1,) frame boundaries of its time bins (the last bin may be shorter).
        failures: per clip, (B,) exponentially forgotten failure counts per bin.
        ended: (C,) exponentially forgotten counts of each clip's ended episodes.
    """

    def __init__(self, num_frames: Sequence[int], config: TrackConfig):
        num_frames = np.asarray(num_frames, dtype=int)
        if num_frames.ndim != 1 or len(num_frames) == 0 or num_frames.min() < 2:
            raise ValueError(f"every clip needs at least 2 frames, got {num_frames.tolist()}")
        self.config = config
        self.num_frames = num_frames
        weights = np.ones(len(num_frames)) if config.clip_weights is None else np.asarray(config.clip_weights, float)
        if weights.shape != num_frames.shape:
            raise ValueError(f"clip_weights has {weights.size} entries for {len(num_frames)} clips")
        self.fixed_clip_probabilities = weights / weights.sum()
        bin_frames = max(1, round(config.adaptive_bin_seconds * config.control_hz))
        # bins cover the frames an episode can start from: all but the last
        self.bin_edges = [np.append(np.arange(0, n - 1, bin_frames), n - 1) for n in num_frames]
        self.failures = [np.zeros(len(edges) - 1) for edges in self.bin_edges]
        self.ended = np.zeros(len(num_frames))
        self._kernel = config.adaptive_lookback_decay ** np.arange(config.adaptive_lookback + 1)

    @property
    def num_clips(self) -> int:
        return len(self.num_frames)

    @property
    def counts_size(self) -> int:
        """How many numbers the counts are: every clip's bins, then each clip's ended episodes."""
        return sum(len(f) for f in self.failures) + self.num_clips

    def attach(self, storage: np.ndarray) -> None:
        """Keep the counts in ``storage`` from now on, which then holds them in place: a float64
        array of :attr:`counts_size` (each clip's ``failures``, then ``ended``), for instance
        shared memory that another process reads. Its contents become the counts."""
        if storage.dtype != np.float64 or storage.shape != (self.counts_size,):
            raise ValueError(f"storage must be a float64 array of shape ({self.counts_size},), "
                             f"got {storage.dtype} {storage.shape}")
        ends = np.cumsum([len(f) for f in self.failures])
        self.failures = np.split(storage[:ends[-1]], ends[:-1])  # views into storage
        self.ended = storage[ends[-1]:]

    @property
    def learning(self) -> bool:
        """Whether ended episodes change the draws (either adaptive mode)."""
        return self.config.start_sampling == "adaptive" or self.config.clip_sampling == "adaptive"

    def failure_rates(self) -> np.ndarray:
        """(C,) share of each clip's recently ended episodes that failed (0 before any ended).

        The failure counts outnumber the ended ones only after a resume, which restores the
        former but not the latter: the rate is then capped at 1 until ended episodes catch up.
        """
        failed = np.array([f.sum() for f in self.failures])
        return np.divide(failed, np.maximum(self.ended, failed), out=np.zeros_like(failed), where=failed > 0)

    def clip_probabilities(self) -> np.ndarray:
        """(C,) probability of drawing each clip at the next start."""
        fixed = self.fixed_clip_probabilities
        if self.config.clip_sampling == "fixed":
            return fixed
        failing = fixed * self.failure_rates()
        if failing.sum() <= 0:
            return fixed
        share = self.config.adaptive_uniform_share
        return share * fixed + (1.0 - share) * failing / failing.sum()

    def bin_probabilities(self, clip: int) -> np.ndarray:
        """(B,) probability of each of ``clip``'s bins, given that a non-frame-0 start is drawn from it."""
        sizes = np.diff(self.bin_edges[clip]).astype(float)
        uniform = sizes / sizes.sum()
        if self.config.start_sampling == "uniform":
            return uniform
        failures = self.failures[clip]
        # a failure in bin b raises bins b, b-1, ..., b-lookback (kernel weights 1, d, d², ...)
        padded = np.concatenate([failures, np.zeros(len(self._kernel) - 1)])
        smoothed = np.array([padded[b:b + len(self._kernel)] @ self._kernel for b in range(len(failures))])
        if smoothed.sum() <= 0:
            return uniform
        share = self.config.adaptive_uniform_share
        return share * uniform + (1.0 - share) * smoothed / smoothed.sum()

    def sample(self, rng: np.random.Generator, count: int,
               clips: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(count,) clip indices and (count,) start frames; ``clips`` fixes the clips instead of drawing them."""
        if clips is not None:
            clips = np.broadcast_to(np.asarray(clips, dtype=int), (count,)).copy()
        elif self.num_clips == 1:
            clips = np.zeros(count, dtype=int)
        else:
            clips = rng.choice(self.num_clips, size=count, p=self.clip_probabilities())
        frames = np.zeros(count, dtype=int)
        if not self.config.random_start:
            return clips, frames
        if self.config.start_sampling == "uniform":
            drawn = rng.integers(0, self.num_frames[clips] - 1)  # never the last frame
        else:
            drawn = np.zeros(count, dtype=int)
            for clip in np.unique(clips):
                rows = np.flatnonzero(clips == clip)
                edges = self.bin_edges[clip]
                bins = rng.choice(len(edges) - 1, size=len(rows), p=self.bin_probabilities(clip))
                drawn[rows] = rng.integers(edges[bins], edges[bins + 1])
        first = rng.random(count) < self.config.rsi_first_frame_prob
        frames[:] = np.where(first, 0, drawn)
        return clips, frames

    def record(self, clips: np.ndarray, frames: np.ndarray, failed: np.ndarray) -> None:
        """Learn from episodes that ended: ``clips``, the frame each ended at, and whether it failed.

        All ended episodes age the counts (forgetting over ``adaptive_memory`` episodes) and count
        as ended for their clip; failures add one to the bin of the frame they ended at.
        """
        clips, frames, failed = (np.asarray(a).reshape(-1) for a in (clips, frames, failed))
        if not self.learning or len(clips) == 0:
            return
        decay = math.exp(-len(clips) / self.config.adaptive_memory)
        for counts in self.failures:
            counts *= decay
        self.ended *= decay
        np.add.at(self.ended, clips.astype(int), 1.0)
        for clip, frame in zip(clips[failed.astype(bool)], frames[failed.astype(bool)]):
            edges = self.bin_edges[clip]
            b = min(int(np.searchsorted(edges, frame, side="right")) - 1, len(edges) - 2)
            self.failures[clip][b] += 1.0

    def stats(self) -> dict[str, np.ndarray]:
        """Per clip: ``failure_mass`` (the forgotten failure counts summed), ``peak_bin_probability``
        (how concentrated the start distribution is; 1/B when uniform with equal bins) and
        ``clip_probability`` (of the next draw), for logs."""
        return {
            "failure_mass": np.array([f.sum() for f in self.failures]),
            "peak_bin_probability": np.array([self.bin_probabilities(c).max() for c in range(self.num_clips)]),
            "clip_probability": self.clip_probabilities(),
        }
