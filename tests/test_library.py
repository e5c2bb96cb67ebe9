"""The motion library: several clips in one model and one batch, each simulation seeing what the
single-clip env shows it."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import crisp_gym  # noqa: F401
from crisp_gym.envs.config import TrackConfig
from crisp_gym.envs.library import MotionLibrary, layout_offsets
from crisp_gym.envs.track import CrispTrackEnv
from crisp_gym.envs.track_vector import CrispTrackVectorEnv
from crisp_gym.registry import BUNDLED_REGISTRY, _read, resolve_clip_names


def test_tag_names_the_tagged_clips_and_bundled_names_all_bundled_clips():
    assert resolve_clip_names("bundled") == sorted(_read(BUNDLED_REGISTRY))
    stairs = resolve_clip_names("stairs")
    assert stairs and all("stairs" in _read(BUNDLED_REGISTRY)[name]["tags"] for name in stairs)
    assert resolve_clip_names("flat_walk") == ["flat_walk"]  # a clip name is not expanded
    with pytest.raises(ValueError, match="tags are"):
        resolve_clip_names("no_such_clip_or_tag")


def test_a_folder_without_a_clip_does_not_hide_a_tag_or_clip_of_its_name(tmp_path, monkeypatch):
    """A run folder called ``bundled`` (or ``flat_walk``) in the working directory must not turn
    ``--clip bundled`` into "bundled is not a complete clip"; a folder that holds a clip wins."""
    from crisp_gym.registry import resolve_clip

    monkeypatch.chdir(tmp_path)
    (tmp_path / "bundled").mkdir()
    (tmp_path / "flat_walk").mkdir()
    (tmp_path / "my_run").mkdir()
    assert resolve_clip_names("bundled") == sorted(_read(BUNDLED_REGISTRY))
    assert resolve_clip("flat_walk") == _read(BUNDLED_REGISTRY)["flat_walk"]["path"]
    assert resolve_clip_names("my_run") == ["my_run"]  # no tag or clip of that name: the folder
    (tmp_path / "flat_walk" / "meta.json").write_text("{}")
    assert resolve_clip("flat_walk") == Path("flat_walk")


def test_layout_leaves_the_gap_between_consecutive_extents():
    extents = [(-20.0, 20.0), (-5.0, 3.0), (0.0, 40.0)]
    offsets = layout_offsets(extents, gap=10.0)
    assert offsets[0].tolist() == [0, 0, 0] and np.all(offsets[:, 1:] == 0)
    shifted = [(lo + o, hi + o) for (lo, hi), o in zip(extents, offsets[:, 0])]
    for (_, end), (start, _) in zip(shifted, shifted[1:]):
        assert start - end == pytest.approx(10.0)


def test_library_regions_do_not_overlap_and_references_carry_their_offsets(sway_clip):
    library = MotionLibrary([str(sway_clip), "stairs_up", "chair_sit"], TrackConfig())
    assert library.names == ["sway", "stairs_up", "chair_sit"]
    single = MotionLibrary("stairs_up", TrackConfig())
    region = library.regions[1]
    rows = region.first + np.arange(region.num_frames)
    np.testing.assert_allclose(library.reference.body_pos[rows], single.reference.body_pos + region.offset)
    np.testing.assert_allclose(library.reference.qvel[rows], single.reference.qvel)
    # each clip's scene geometry (x extent of its boxes) stays clear of every other clip's pelvis path
    for i, r in enumerate(library.regions):
        path_x = library.reference.body_pos[r.first:r.first + r.num_frames, 0, 0]
        for j, other in enumerate(library.clips):
            if i != j:
                xs = np.concatenate([b.corners()[:, 0] for b in other.boxes]) + library.regions[j].offset[0]
                assert path_x.min() > xs.max() + 5 or path_x.max() < xs.min() - 5
    with pytest.raises(ValueError, match="more than once"):
        MotionLibrary(["stairs_up", "stairs_up"], TrackConfig())


@pytest.mark.parametrize("scene_aware", [False, True])
def test_library_simulation_matches_the_single_clip_env_step_by_step(sway_clip, scene_aware):
    """Simulations of the library's second and third clips (shifted by tens of metres) see the
    same observations, rewards and physics as the single-clip env from the same start."""
    clips = [str(sway_clip), "stairs_up", "chair_sit"]
    starts = np.array([40, 60])
    venv = CrispTrackVectorEnv(2, clip=clips, scene_aware=scene_aware, num_threads=1)
    vobs, vinfo = venv.reset(seed=0, options={"clip": ["stairs_up", "chair_sit"], "start_frame": starts})
    assert vinfo["clip"].tolist() == [1, 2]
    singles = [CrispTrackEnv(clip=name, scene_aware=scene_aware) for name in ("stairs_up", "chair_sit")]
    sobs = [env.reset(seed=0, options={"start_frame": int(s)})[0] for env, s in zip(singles, starts)]
    rng = np.random.default_rng(0)
    for _ in range(15):
        for key in vobs:
            got, expected = vobs[key], np.stack([o[key] for o in sobs])
            if key == "points":  # equidistant samples may swap places: compare the sets
                got, expected = _sorted_rows(got), _sorted_rows(expected)
            np.testing.assert_allclose(got, expected, atol=1e-5)
        actions = rng.uniform(-0.05, 0.05, (2, 69)).astype(np.float32)
        vobs, vrew, vterm, vtrunc, vinfo = venv.step(actions)
        results = [env.step(a) for env, a in zip(singles, actions)]
        sobs = [r[0] for r in results]
        np.testing.assert_allclose(vrew, [r[1] for r in results], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(vinfo["max_body_error"], [r[4]["max_body_error"] for r in results], atol=1e-6)
        assert vinfo["farthest_body"].tolist() == [r[4]["farthest_body"] for r in results]
        assert vterm.tolist() == [r[2] for r in results] and not vtrunc.any()
    for env, offset in zip(singles, (venv.task.library.regions[1].offset, venv.task.library.regions[2].offset)):
        np.testing.assert_allclose(env.data.qpos[:2] + offset[:2], venv._fields["qpos"][singles.index(env), :2],
                                   atol=1e-6)


def _sorted_rows(points: np.ndarray) -> np.ndarray:
    """(N, P, 3) points with each simulation's points in lexicographic order (rounded to 0.1 mm)."""
    out = np.empty_like(points)
    for i, p in enumerate(points):
        out[i] = p[np.lexsort(np.round(p, 4).T[::-1])]
    return out


def test_library_episodes_end_at_their_own_clips_last_frame():
    venv = gym.make_vec("CrispTrack-v0", num_envs=2, vectorization_mode="vector_entry_point",
                        clip=["stairs_up", "flat_walk"])
    lengths = venv.task.num_frames
    venv.reset(seed=0, options={"clip": [0, 1], "start_frame": [lengths[0] - 3, lengths[1] - 4]})
    zero = np.zeros((2, 69))
    _, _, _, truncated, _ = venv.step(zero)
    assert truncated.tolist() == [False, False]
    _, _, _, truncated, info = venv.step(zero)
    assert truncated.tolist() == [True, False] and info["final_info"][0]["clip"] == 0
    _, _, _, truncated, info = venv.step(zero)
    assert truncated[1] and info["final_info"][1]["frame"] == lengths[1] - 1


def test_resets_draw_clips_by_weight():
    env = CrispTrackEnv(clip=["stairs_up", "flat_walk"], clip_weights=(3.0, 1.0))
    clips = np.array([env.reset(seed=s)[1]["clip"] for s in range(400)])
    assert 0.68 < np.mean(clips == 0) < 0.82  # 3:1 → 0.75
    with pytest.raises(ValueError, match="clip_weights has 3 entries"):
        CrispTrackEnv(clip=["stairs_up", "flat_walk"], clip_weights=(1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="clip must be"):
        env.reset(options={"clip": "chair_sit"})
