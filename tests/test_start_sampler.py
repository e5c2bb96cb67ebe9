"""The start sampler as a sampler: properties that hold for any clips, weights and failure history."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crisp_gym.envs.config import TrackConfig
from crisp_gym.envs.start_sampler import StartSampler

clip_lengths = st.lists(st.integers(2, 400), min_size=1, max_size=5)
failure_history = st.lists(st.tuples(st.integers(0, 4), st.floats(0, 1), st.booleans()), max_size=60)


def _adaptive(**overrides) -> TrackConfig:
    return TrackConfig(start_sampling="adaptive", **overrides)


def _replay(sampler: StartSampler, history) -> None:
    """Feed ``(clip, position in the clip, failed)`` episodes to ``record``."""
    for clip, position, failed in history:
        clip = clip % sampler.num_clips
        frame = int(position * (sampler.num_frames[clip] - 1))
        sampler.record(np.array([clip]), np.array([frame]), np.array([failed]))


@settings(max_examples=60, deadline=None)
@given(lengths=clip_lengths, history=failure_history, seed=st.integers(0, 2**31 - 1))
def test_probabilities_are_distributions_with_a_uniform_floor(lengths, history, seed):
    config = _adaptive()
    sampler = StartSampler(lengths, config)
    _replay(sampler, history)
    for clip, edges in enumerate(sampler.bin_edges):
        p = sampler.bin_probabilities(clip)
        sizes = np.diff(edges)
        assert p.shape == sizes.shape and np.all(sizes > 0)
        assert p.sum() == pytest.approx(1.0)
        # never below the uniform share of each bin's frames
        assert np.all(p >= config.adaptive_uniform_share * sizes / sizes.sum() - 1e-12)
    clips, frames = sampler.sample(np.random.default_rng(seed), 200)
    assert np.all((frames >= 0) & (frames <= np.asarray(lengths)[clips] - 2))  # never the last frame


@settings(max_examples=30, deadline=None)
@given(lengths=clip_lengths, seed=st.integers(0, 2**31 - 1))
def test_without_failures_adaptive_draws_match_uniform_draws_in_distribution(lengths, seed):
    """No failure recorded: every startable frame of a clip is equally likely (bins weigh by size)."""
    sampler = StartSampler(lengths, _adaptive(rsi_first_frame_prob=0.0))
    for clip in range(sampler.num_clips):
        sizes = np.diff(sampler.bin_edges[clip])
        np.testing.assert_allclose(sampler.bin_probabilities(clip), sizes / sizes.sum())


def test_frame_frequencies_match_the_bin_probabilities():
    """A chi-square-style check of the draws against the stated probabilities after failures."""
    sampler = StartSampler([301], _adaptive(rsi_first_frame_prob=0.0))
    sampler.record(np.array([0, 0, 0]), np.array([200, 205, 40]), np.array([True, True, True]))
    rng = np.random.default_rng(0)
    _, frames = sampler.sample(rng, 200_000)
    counts = np.histogram(frames, bins=sampler.bin_edges[0])[0]
    expected = sampler.bin_probabilities(0) * len(frames)
    assert np.max(np.abs(counts - expected) / np.sqrt(expected)) < 5


def test_a_failure_raises_its_bin_and_the_bins_before_it_only():
    config = _adaptive(adaptive_bin_seconds=1.0, adaptive_lookback=2, adaptive_lookback_decay=0.5)
    sampler = StartSampler([301], config)  # 30-frame bins
    before = sampler.bin_probabilities(0)
    sampler.record(np.array([0]), np.array([215]), np.array([True]))  # bin 7
    after = sampler.bin_probabilities(0)
    raised = np.flatnonzero(after > before + 1e-12)
    assert raised.tolist() == [5, 6, 7]
    assert after[7] > after[6] > after[5]  # weights 1, 0.5, 0.25
    assert np.argmax(after) == 7


def test_successes_forget_failures():
    sampler = StartSampler([301], _adaptive(adaptive_memory=50.0))
    sampler.record(np.array([0]), np.array([100]), np.array([True]))
    peaked = sampler.bin_probabilities(0).max()
    sampler.record(np.zeros(500, dtype=int), np.full(500, 300), np.zeros(500, dtype=bool))
    assert sampler.failures[0].sum() == pytest.approx(np.exp(-10.0), rel=1e-6)
    # a single failure still decides the adaptive share, however faded: nothing else competes
    assert sampler.bin_probabilities(0).max() == pytest.approx(peaked)
    sampler.record(np.array([0]), np.array([20]), np.array([True]))  # a fresh failure dominates the old one
    assert np.argmax(sampler.bin_probabilities(0)) == 0


def test_uniform_mode_ignores_failures_and_frame_zero_share_holds():
    sampler = StartSampler([101, 51], TrackConfig(rsi_first_frame_prob=0.25, clip_weights=(1.0, 3.0)))
    sampler.record(np.array([0]), np.array([50]), np.array([True]))
    assert sampler.failures[0].sum() == 0
    clips, frames = sampler.sample(np.random.default_rng(1), 40_000)
    assert np.mean(clips == 1) == pytest.approx(0.75, abs=0.01)
    assert np.mean(frames == 0) == pytest.approx(0.25 + 0.75 * (np.mean(clips == 0) / 100 + np.mean(clips == 1) / 50),
                                               abs=0.01)


def test_same_seed_same_starts():
    def draws():
        sampler = StartSampler([120, 80], _adaptive())
        sampler.record(np.array([1]), np.array([60]), np.array([True]))
        return sampler.sample(np.random.default_rng(7), 50)
    (c1, f1), (c2, f2) = draws(), draws()
    assert c1.tolist() == c2.tolist() and f1.tolist() == f2.tolist()


@settings(max_examples=60, deadline=None)
@given(lengths=clip_lengths, history=failure_history,
       weights=st.lists(st.floats(0.1, 10.0), min_size=5, max_size=5))
def test_adaptive_clip_probabilities_mix_weights_and_failure_rates(lengths, history, weights):
    """A distribution; never below the weights' share; with equal weights, a clip that fails
    more often is drawn at least as often; a clip that never failed gets the floor exactly."""
    config = TrackConfig(clip_sampling="adaptive", clip_weights=tuple(weights[:len(lengths)]))
    sampler = StartSampler(lengths, config)
    _replay(sampler, history)
    p, fixed = sampler.clip_probabilities(), sampler.fixed_clip_probabilities
    assert p.sum() == pytest.approx(1.0) and np.all(p >= config.adaptive_uniform_share * fixed - 1e-12)
    rates = sampler.failure_rates()
    assert np.all((rates >= 0) & (rates <= 1))
    if rates.sum() == 0:
        np.testing.assert_allclose(p, fixed)  # nothing failed: the weights alone
    else:
        never = rates == 0
        np.testing.assert_allclose(p[never], config.adaptive_uniform_share * fixed[never])
        equal = StartSampler(lengths, TrackConfig(clip_sampling="adaptive"))
        _replay(equal, history)
        order = np.argsort(equal.failure_rates())
        assert np.all(np.diff(equal.clip_probabilities()[order]) >= -1e-12)


def test_failure_rates_count_ended_episodes_per_clip():
    sampler = StartSampler([100, 100], TrackConfig(clip_sampling="adaptive", adaptive_memory=1e9))
    failed = np.array([True] * 3 + [False] * 7 + [True] * 1 + [False] * 9)
    sampler.record(np.array([0] * 10 + [1] * 10), np.full(20, 50), failed)
    np.testing.assert_allclose(sampler.failure_rates(), [0.3, 0.1], rtol=1e-6)
    # share 0.2 of equal weights, the rest split 3 : 1 by the rates
    np.testing.assert_allclose(sampler.clip_probabilities(), [0.1 + 0.8 * 0.75, 0.1 + 0.8 * 0.25], rtol=1e-6)
    clips, _ = sampler.sample(np.random.default_rng(0), 40_000)
    assert np.mean(clips == 0) == pytest.approx(0.7, abs=0.01)
    # uniform frames with adaptive clips: the sampler learns although start_sampling is uniform
    assert sampler.config.start_sampling == "uniform" and sampler.learning
    # fixed clips: the weights, whatever failed
    fixed = StartSampler([100, 100], TrackConfig(start_sampling="adaptive", clip_weights=(1.0, 3.0)))
    fixed.record(np.zeros(10, dtype=int), np.full(10, 50), np.ones(10, dtype=bool))
    np.testing.assert_allclose(fixed.clip_probabilities(), [0.25, 0.75])
    # after a resume the failure counts are back but not the ended counts: rates capped at 1
    resumed = StartSampler([100, 100], TrackConfig(clip_sampling="adaptive"))
    resumed.failures = [f.copy() for f in sampler.failures]
    np.testing.assert_allclose(resumed.failure_rates(), [1.0, 1.0])


def test_bad_configuration_is_refused():
    with pytest.raises(ValueError, match="start_sampling"):
        TrackConfig(start_sampling="greedy")
    with pytest.raises(ValueError, match="clip_sampling"):
        TrackConfig(clip_sampling="greedy")
    with pytest.raises(ValueError, match="clip_weights"):
        TrackConfig(clip_weights=(0.0, 0.0))
    with pytest.raises(ValueError, match="at least 2 frames"):
        StartSampler([1], TrackConfig())


def test_counts_kept_in_given_storage_are_the_counts():
    """``attach``: the storage's contents become the counts, and later records land in it."""
    sampler = StartSampler([61, 31], _adaptive(adaptive_bin_seconds=1.0))
    assert sampler.counts_size == 2 + 1 + 2  # bins of 30 frames over 60 and 30 start frames, then ended
    storage = np.arange(5, dtype=np.float64)
    sampler.attach(storage)
    assert [f.tolist() for f in sampler.failures] == [[0.0, 1.0], [2.0]] and sampler.ended.tolist() == [3.0, 4.0]
    twin = StartSampler([61, 31], _adaptive(adaptive_bin_seconds=1.0))
    twin.failures, twin.ended = [np.array([0.0, 1.0]), np.array([2.0])], np.array([3.0, 4.0])
    for s in (sampler, twin):
        s.record(np.array([0, 1, 0]), np.array([45, 10, 3]), np.array([True, True, False]))
    np.testing.assert_array_equal(storage, np.concatenate([*twin.failures, twin.ended]))
    rng, twin_rng = np.random.default_rng(2), np.random.default_rng(2)
    assert [a.tolist() for a in sampler.sample(rng, 30)] == [a.tolist() for a in twin.sample(twin_rng, 30)]
    with pytest.raises(ValueError, match=r"float64 array of shape \(5,\)"):
        sampler.attach(np.zeros(4))
