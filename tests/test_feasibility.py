"""The batched env's snapshots and the feasibility search built on them."""

from pathlib import Path

import numpy as np
import pytest

from crisp_gym.cli import main as crisp
from crisp_gym.envs.track_vector import CrispTrackVectorEnv
from crisp_gym.feasibility import SearchConfig, pd_reference_errors, search_clip, search_env

FLAT_WALK_POLICY = Path(__file__).parents[1] / "assets" / "policies" / "flat_walk"


def _roll(env: CrispTrackVectorEnv, actions: np.ndarray):
    out = []
    for action in actions:
        obs, reward, _, _, info = env.step(action)
        out.append((env.snapshot().physics["qpos"], obs["targets"], reward, info["max_body_error"]))
    return out


def test_a_restored_snapshot_continues_as_the_simulation_it_was_taken_from(sway_clip):
    env = CrispTrackVectorEnv(num_envs=4, clip=str(sway_clip), num_threads=1, autoreset_mode="next_step")
    env.reset(seed=0, options={"start_frame": [0, 10, 20, 30]})
    rng = np.random.default_rng(0)
    _roll(env, rng.normal(0, 0.1, (3, 4, 69)))
    last_obs, *_ = env.step(rng.normal(0, 0.1, (4, 69)))
    snapshot = env.snapshot()
    actions = rng.normal(0, 0.1, (5, 4, 69))
    original = _roll(env, actions)

    restored_obs = env.restore(snapshot)
    for key, value in last_obs.items():  # a restore observes what the step into that state did
        np.testing.assert_array_equal(restored_obs[key], value)
    for a, b in zip(_roll(env, actions), original, strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)  # bit for bit: the warm start is part of the state

    # branching: one state to several simulations, each continuing as its source did
    rows = np.array([2, 2, 0, 1])
    env.restore(snapshot, rows)
    for a, b in zip(_roll(env, actions[:, rows]), original, strict=True):
        np.testing.assert_array_equal(a[0], b[0][rows])
        np.testing.assert_array_equal(a[3], b[3][rows])


def test_restore_rejects_rows_that_do_not_fit(sway_clip):
    env = CrispTrackVectorEnv(num_envs=2, clip=str(sway_clip), num_threads=1)
    env.reset(seed=0)
    snapshot = env.snapshot(np.array([1]))
    with pytest.raises(ValueError, match="rows"):
        env.restore(snapshot)  # a one-state snapshot has no row 1
    with pytest.raises(ValueError, match="rows"):
        env.restore(snapshot, np.zeros(3, dtype=int))


def test_found_actions_replay_in_the_env_and_a_search_is_reproducible():
    config = SearchConfig(population=32, elites=4, sigma=0.3, retries=2, num_threads=1, seed=3)
    result = search_clip("flat_walk", 150, config)
    env = search_env("flat_walk", 1, 1)
    last = int(env.task.num_frames[0]) - 1
    assert result.reached == 150 + len(result.actions) and result.reached > 150
    assert result.whole == (result.reached == last)
    assert result.max_body_error.max() <= 0.5

    env.reset(seed=0, options={"start_frame": 150})
    for action, qpos, error in zip(result.actions, result.qpos, result.max_body_error, strict=True):
        _, _, terminated, _, info = env.step(action[None])
        np.testing.assert_array_equal(env.snapshot().physics["qpos"][0], qpos)
        assert info["max_body_error"][0] == error and not terminated[0]

    again = search_clip("flat_walk", 150, config)
    np.testing.assert_array_equal(again.actions, result.actions)
    other = search_clip("flat_walk", 150, SearchConfig(population=32, elites=4, sigma=0.3, retries=2, num_threads=1,
                                                       seed=4))
    assert not np.array_equal(other.actions[:4], result.actions[:4])


def test_a_search_tracks_further_than_the_pd_reference():
    """From frame 0 the PD reference alone falls within two seconds of flat_walk; drawing around it
    and keeping the best branches gets much further."""
    pd_frames = int(np.sum(pd_reference_errors("flat_walk", 0) <= 0.5))
    config = SearchConfig(population=64, elites=16, sigma=0.3, retries=12, num_threads=1)
    result = search_clip("flat_walk", 0, config)
    assert pd_frames < 60  # 37 frames
    assert result.reached >= pd_frames + 30  # 84 frames


def test_the_cli_searches_around_a_policy_and_writes_its_result(tmp_path, capsys):
    """Around the shipped flat_walk policy (which tracks the whole clip) a search reaches the end."""
    out = tmp_path / "search"
    assert crisp(["feasibility", "flat_walk", "--start-frame", "120", "--policy", str(FLAT_WALK_POLICY),
                  "--search.population", "8", "--search.elites", "2", "--search.num-threads", "1", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "feasible for this humanoid from frame 120" in printed and "The PD reference alone: to frame" in printed
    saved = np.load(out / "search.npz")
    assert not bool(saved["env_velocity_feedforward"])  # the flat_walk policy's own control law
    last = int(search_env("flat_walk", 1, 1).task.num_frames[0]) - 1
    assert bool(saved["whole"]) and int(saved["reached"]) == last and saved["actions"].shape == (last - 120, 69)
    assert (out / "search.png").stat().st_size > 0


def test_the_cli_reports_bad_input(capsys):
    assert crisp(["feasibility", "no_such_clip"]) == 2
    assert "no_such_clip" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:  # tyro reports a config it cannot build as a usage error
        crisp(["feasibility", "flat_walk", "--search.population", "4", "--search.elites", "8"])
    assert exit_.value.code == 2 and "elites must be in [1, population=4]" in capsys.readouterr().err
    assert crisp(["feasibility", "flat_walk", "--start-frame", "500", "--search.population", "4",
                  "--search.elites", "2"]) == 2
    assert "start_frame" in capsys.readouterr().err
