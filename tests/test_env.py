import contextlib

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode
from threadpoolctl import ThreadpoolController, threadpool_limits

import crisp_gym  # noqa: F401
from crisp_gym.envs.config import TrackConfig
from crisp_gym.envs.track import CrispTrackEnv
from crisp_gym.envs.track_vector import CrispTrackVectorEnv
from crisp_gym.envs.tracking import reward_term_names
from crisp_gym.registry import BUNDLED_REGISTRY, _read


def bundled_clip_names() -> list[str]:
    return sorted(_read(BUNDLED_REGISTRY))


def test_bundled_clips_are_registered():
    assert {"flat_walk", "stairs_up", "platform_step", "chair_sit"} <= set(bundled_clip_names())


@pytest.mark.parametrize("scene_aware", [False, True])
def test_check_env(sway_clip, scene_aware):
    env = gym.make("CrispTrack-v0", clip=str(sway_clip), scene_aware=scene_aware)
    check_env(env.unwrapped, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    assert obs["proprio"].shape == (361,) and obs["targets"].shape == (5, 432)
    assert ("points" in obs) == scene_aware
    if scene_aware:
        assert obs["points"].shape == (128, 3)
        # points are relative to the pelvis: the nearest lies on the floor, about a pelvis height below
        assert np.min(np.linalg.norm(obs["points"], axis=1)) < 1.2


@pytest.mark.parametrize("clip", ["sway", *bundled_clip_names()])
def test_reset_matches_reference_and_pd_tracking_runs_clean(sway_clip, clip):
    env = CrispTrackEnv(clip=str(sway_clip) if clip == "sway" else clip)
    frames = np.linspace(0, env.task.num_frames[0] - 2, 5).astype(int)
    for frame in frames:
        _, info = env.reset(seed=1, options={"start_frame": int(frame)})
        assert info["max_body_error"] < 0.01  # the model and the motion agree
    env.reset(seed=0, options={"start_frame": 0})
    zero = np.zeros(69, dtype=np.float32)
    steps = 0
    while True:
        _, reward, terminated, truncated, info = env.step(zero)
        steps += 1
        assert np.isfinite(reward) and np.all(np.isfinite(env.data.qpos))
        assert not any(w.number for w in env.data.warning), "MuJoCo warned"
        terms = {k: v for k, v in info.items() if k.startswith("reward_")}
        assert set(terms) == {f"reward_{t}" for t in ("pos", "rot", "vel", "ang_vel", "height", "energy")}
        assert reward == pytest.approx(sum(terms.values()))
        if terminated or truncated:
            break
    assert steps <= env.task.num_frames[0] - 1
    assert info["success"] == truncated and (truncated or info["max_body_error"] > 0.5)
    # the farthest body is the one the error is measured on
    row = env.task.library.global_frames(env._clip, env._frame)[0]
    distances = np.linalg.norm(env.task.reference.body_pos[row] - env._state().body_pos[0], axis=-1)
    assert info["farthest_body"] == int(np.argmax(distances))
    assert info["max_body_error"] == pytest.approx(distances.max())


def test_single_and_batched_envs_agree_step_by_step(sway_clip):
    starts = np.array([0, 7, 21])
    venv = CrispTrackVectorEnv(len(starts), clip=str(sway_clip), scene_aware=True, num_threads=1)
    vobs, _ = venv.reset(seed=0, options={"start_frame": starts})
    singles = [CrispTrackEnv(clip=str(sway_clip), scene_aware=True) for _ in starts]
    sobs = [env.reset(seed=0, options={"start_frame": int(s)})[0] for env, s in zip(singles, starts)]
    rng = np.random.default_rng(0)
    for _ in range(10):
        for key in vobs:
            np.testing.assert_allclose(vobs[key], np.stack([o[key] for o in sobs]), atol=1e-6)
        actions = rng.uniform(-0.05, 0.05, (len(starts), 69)).astype(np.float32)
        vobs, vrew, vterm, vtrunc, vinfo = venv.step(actions)
        results = [env.step(a) for env, a in zip(singles, actions)]
        sobs = [r[0] for r in results]
        np.testing.assert_allclose(vrew, [r[1] for r in results], rtol=1e-9, atol=1e-9)
        for term in (k for k in vinfo if k.startswith("reward_")):
            np.testing.assert_allclose(vinfo[term], [r[4][term] for r in results],
                                       rtol=1e-9, atol=1e-9)
        assert not vterm.any() and not vtrunc.any()


def test_a_reset_simulation_runs_exactly_as_a_fresh_one():
    """A reset leaves nothing of the episode before (the solver's warm start, the time, applied
    forces): a batch that ran and fell before its reset steps bit for bit as a new batch."""
    rng = np.random.default_rng(0)
    used = CrispTrackVectorEnv(3, clip="flat_walk", num_threads=1)
    used.reset(seed=0)
    for _ in range(40):  # large actions: falls, contacts and same-step resets on the way
        used.step(rng.uniform(-1, 1, (3, 69)).astype(np.float32))
    fresh = CrispTrackVectorEnv(3, clip="flat_walk", num_threads=1)
    starts = {"start_frame": [0, 9, 30]}
    runs = [env.reset(seed=1, options=starts)[0] for env in (used, fresh)]
    for key in runs[0]:
        np.testing.assert_array_equal(runs[0][key], runs[1][key])
    for _ in range(15):
        actions = rng.uniform(-0.1, 0.1, (3, 69)).astype(np.float32)
        (obs_a, rew_a, *_), (obs_b, rew_b, *_) = used.step(actions), fresh.step(actions)
        for key in obs_a:
            np.testing.assert_array_equal(obs_a[key], obs_b[key])
        np.testing.assert_array_equal(rew_a, rew_b)


@pytest.mark.parametrize("autoreset_mode", ["same_step", "next_step"])
def test_kept_start_observations_are_what_the_reset_state_gives(sway_clip, autoreset_mode):
    """The observation of a simulation just reset is kept per start frame and reused: it must be,
    bit for bit, what the env's observation function gives on the reset state (scene points too)."""
    env = CrispTrackVectorEnv(12, clip=str(sway_clip), scene_aware=True, num_threads=1,
                              autoreset_mode=autoreset_mode)
    rng = np.random.default_rng(3)
    obs, _ = env.reset(seed=0)
    starts = 12
    for _ in range(60):  # large actions: many falls, so many resets
        was_reset = env._needs_reset.copy()
        obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, (12, 69)).astype(np.float32))
        reset = was_reset if autoreset_mode == "next_step" else terminated | truncated
        ids = np.flatnonzero(reset)
        starts += len(ids)
        if len(ids):
            env._forward(ids)  # the reset state's derived fields (a reset leaves them to the next step)
            expected = env.task.observe(env._state(ids), env._clip[ids], env._frame[ids])
            for key in obs:
                np.testing.assert_array_equal(obs[key][ids], expected[key])
    kept = int(env._start_obs.known.sum())
    assert starts > 40 and kept < starts  # resets happened, and some started where one had before


def test_reset_simulations_step_alike_without_a_forward_pass(sway_clip):
    """A reset leaves the derived fields to the next step, which computes its own forward pass:
    the trajectories must be those of an env that brings every reset up to date at once."""
    plain = CrispTrackVectorEnv(8, clip=str(sway_clip), num_threads=1)
    eager = CrispTrackVectorEnv(8, clip=str(sway_clip), num_threads=1)
    reset_sims = eager._reset_sims

    def reset_and_forward(ids, clips, frames):
        reset_sims(ids, clips, frames)
        eager._forward(ids)

    eager._reset_sims = reset_and_forward
    rng = np.random.default_rng(5)
    plain.reset(seed=1)
    eager.reset(seed=1)
    resets = 0
    for _ in range(40):  # large actions: many falls, so many resets
        action = rng.uniform(-1, 1, (8, 69))
        a, b = plain.step(action), eager.step(action)
        for key in a[0]:
            np.testing.assert_array_equal(a[0][key], b[0][key])
        np.testing.assert_array_equal(a[1], b[1])
        np.testing.assert_array_equal(a[2], b[2])
        resets += int(a[2].sum() + a[3].sum())
    assert resets > 10


def test_make_vec_and_same_step_autoreset(sway_clip):
    venv = gym.make_vec("CrispTrack-v0", num_envs=4, vectorization_mode="vector_entry_point", clip=str(sway_clip))
    assert isinstance(venv, CrispTrackVectorEnv)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP == venv.autoreset_mode
    num_frames = int(venv.task.num_frames[0])
    venv.reset(seed=0, options={"start_frame": num_frames - 3})
    zero = np.zeros((4, 69))
    venv.step(zero)
    obs, _, terminated, truncated, info = venv.step(zero)  # reaches the last frame
    assert truncated.all() and not terminated.any() and info["success"].all()
    assert info["_final_obs"].all() and info["final_info"][0]["success"]
    # the returned observation already belongs to the next episode
    assert not np.allclose(obs["targets"], np.stack([o["targets"] for o in info["final_obs"]]))
    assert np.all(venv._frame < num_frames - 1)


def test_the_envs_numpy_work_runs_on_one_blas_thread_and_the_callers_setting_stays(sway_clip, monkeypatch):
    # OpenBLAS's workers spin after a threaded product and take cores from MuJoCo's threads.
    blas = ThreadpoolController().select(user_api="blas")
    if not blas.lib_controllers:
        pytest.skip("numpy runs on no BLAS library that threadpoolctl can see")
    venv = CrispTrackVectorEnv(4, clip=str(sway_clip))
    observe, seen = venv.task.observe, []

    def observe_and_count_threads(*args):
        seen.append({lib["num_threads"] for lib in blas.info()})
        return observe(*args)

    monkeypatch.setattr(venv.task, "observe", observe_and_count_threads)
    with threadpool_limits(limits=2, user_api="blas"):
        venv.reset(seed=0)
        venv.step(np.zeros((4, 69)))
        venv.restore(venv.snapshot())
        after = {lib["num_threads"] for lib in blas.info()}
    assert len(seen) >= 3 and all(threads == {1} for threads in seen)
    assert after == {2}


def test_bad_arguments_get_clear_errors(sway_clip):
    with pytest.raises(TypeError, match="unexpected keyword argument 'not_an_option'.*valid ones are"):
        CrispTrackEnv(clip=str(sway_clip), not_an_option=1)
    with pytest.raises(ValueError, match="unknown clip"):
        CrispTrackEnv(clip="no_such_clip")
    env = CrispTrackEnv(clip=str(sway_clip))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="69"):
        env.step(np.zeros(12))
    with pytest.raises(ValueError, match="start_frame"):
        env.reset(options={"start_frame": 10_000})
    with pytest.raises(ValueError, match="multiple"):
        CrispTrackEnv(clip=str(sway_clip), control_hz=50.0)


def test_rsi_draws_frame_zero_about_ten_percent(sway_clip):
    env = CrispTrackEnv(clip=str(sway_clip))
    starts = np.array([env.reset(seed=s)[1]["start_frame"] for s in range(400)])
    share = np.mean(starts == 0)
    assert 0.06 < share < 0.16  # 10 % plus the uniform draw's 1/(T-1)
    assert starts.max() <= env.task.num_frames[0] - 2 and len(np.unique(starts)) > 20


def test_render_rgb_array(sway_clip):
    env = CrispTrackEnv(clip=str(sway_clip), render_mode="rgb_array", render_width=160, render_height=120)
    env.reset(seed=0)
    image = env.render()
    env.close()
    assert image.shape == (120, 160, 3) and image.dtype == np.uint8 and image.std() > 5
    sky, ground = image[:12].astype(float), image[-20:].astype(float)
    assert sky.mean() > 60 and sky[..., 2].mean() > sky[..., 0].mean()  # a blue sky, not black
    assert ground.std() > 15  # the floor is checkered, not one flat colour


def test_nearest_points_match_brute_force() -> None:
    """The KD-tree query returns the ``count`` samples nearest the pelvis, nearest first, as a
    full distance sort does; fewer samples than slots repeat the farthest."""
    from scipy.spatial import cKDTree

    from crisp_gym.envs import quat
    from crisp_gym.envs.tracking import nearest_points

    rng = np.random.default_rng(0)
    points = rng.uniform(-3, 3, (500, 3))
    n = 4
    body_pos = rng.normal(0, 1, (n, 24, 3))
    body_quat = rng.normal(size=(n, 24, 4))
    body_quat /= np.linalg.norm(body_quat, axis=-1, keepdims=True)
    got = nearest_points(body_pos[:, 0], body_quat[:, 0], cKDTree(points), 16)
    yaw_inverse = quat.conjugate(quat.yaw_quat(body_quat[:, 0]))[:, None]
    for i in range(n):
        order = np.argsort(np.linalg.norm(points - body_pos[i, 0], axis=1))[:16]
        expected = quat.rotate(np.broadcast_to(yaw_inverse[i], (16, 4)), points[order] - body_pos[i, 0])
        np.testing.assert_allclose(got[i], expected, atol=1e-12)
    few = nearest_points(body_pos[:, 0], body_quat[:, 0], cKDTree(points[:3]), 5)
    np.testing.assert_allclose(few[:, 3:], few[:, 2:3].repeat(2, axis=1))


def test_torchrl_gym_env_entry_point(sway_clip):
    """TorchRL's own GymEnv passes frameskip first and falls back on Python's wording for an
    unknown keyword; the env it builds passes TorchRL's spec check."""
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    env = GymEnv("CrispTrack-v0", clip=str(sway_clip))
    check_env_specs(env)
    env.close()


@pytest.mark.parametrize("w_root_pos", [0.0, 1.0])
def test_torchrl_wraps_the_batched_env(sway_clip, w_root_pos):
    """``GymWrapper(gym.make_vec(...))``: TorchRL reads the infos into fixed specs, so a reset's
    info has a step's keys (the root position term's too, when weighted); its spec check passes, a
    rollout runs through episode ends, and the reward is the sum of the terms in the info."""
    from torchrl.envs import GymWrapper
    from torchrl.envs.utils import check_env_specs

    venv = gym.make_vec("CrispTrack-v0", num_envs=3, vectorization_mode="vector_entry_point", clip=str(sway_clip),
                        w_root_pos=w_root_pos)
    _, reset_info = venv.reset(seed=0)
    _, _, _, _, step_info = venv.step(np.zeros(venv.action_space.shape))
    assert {k for k in step_info if not k.startswith(("final", "_final"))} == set(reset_info)
    terms = reward_term_names(TrackConfig(w_root_pos=w_root_pos))
    assert ("reward_root_pos" in reset_info) == (w_root_pos > 0) and {f"reward_{t}" for t in terms} <= set(reset_info)
    single = CrispTrackEnv(clip=str(sway_clip), w_root_pos=w_root_pos)
    _, single_reset = single.reset(seed=0)
    single_step = single.step(np.zeros(single.action_space.shape))[-1]
    assert set(single_step) == set(single_reset) >= {f"reward_{t}" for t in terms}
    env = GymWrapper(venv)
    check_env_specs(env)
    zero = lambda td: td.set("action", torch.zeros(env.action_spec.shape))  # noqa: E731 - the PD reference
    rollout = env.rollout(70, zero, break_when_any_done=False)  # the 60-frame clip ends inside it
    assert rollout.batch_size == (3, 70) and rollout["next", "done"].any()
    going = ~rollout["next", "done"].squeeze(-1).numpy()  # an episode's end step reads the next one's reset
    np.testing.assert_allclose(rollout["next", "reward"].squeeze(-1).numpy()[going],
                               sum(rollout["next", f"reward_{t}"].numpy() for t in terms)[going],
                               rtol=1e-5, atol=1e-5)
    env.close()


def test_next_step_autoreset_for_gymnasium_wrappers(sway_clip):
    """``autoreset_mode="next_step"``: an episode's last step keeps its observation, the next step
    is the reset (reward 0, action ignored), and gymnasium's vector wrappers accept the env; the
    steps between resets are those of the SAME_STEP env."""
    from gymnasium.wrappers.vector import FlattenObservation, NormalizeObservation

    kwargs = dict(num_envs=2, vectorization_mode="vector_entry_point", clip=str(sway_clip))
    nxt = gym.make_vec("CrispTrack-v0", autoreset_mode="next_step", **kwargs)
    same = gym.make_vec("CrispTrack-v0", **kwargs)
    assert nxt.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert same.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    start = {"start_frame": [50, 55]}
    obs_n, _ = nxt.reset(seed=0, options=start)
    obs_s, _ = same.reset(seed=0, options=start)
    action = np.zeros(nxt.action_space.shape)
    ended = None
    for _ in range(12):
        obs_n, rew_n, term_n, trunc_n, info_n = nxt.step(action)
        if ended is not None:  # the step after an episode ended is its reset
            assert rew_n[ended] == 0 and not term_n[ended] and not trunc_n[ended]
            assert info_n["frame"][ended] == info_n["start_frame"][ended]
            break
        obs_s, rew_s, term_s, trunc_s, info_s = same.step(action)
        np.testing.assert_allclose(rew_n, rew_s)
        done = term_n | trunc_n
        np.testing.assert_array_equal(done, term_s | trunc_s)
        for k in obs_n:  # the finished env keeps its last observation, the SAME_STEP one reports it as final
            want = np.stack([info_s["final_obs"][i][k] if done[i] else obs_s[k][i] for i in range(2)])
            np.testing.assert_allclose(obs_n[k], want)
        if done.any():
            ended = int(np.flatnonzero(done)[0])
    assert ended is not None
    wrapped = NormalizeObservation(FlattenObservation(nxt))
    flat, _ = wrapped.reset(seed=1)
    assert flat.shape[0] == 2 and np.all(np.isfinite(flat))
    wrapped.step(action)
    with pytest.raises(ValueError, match="autoreset_mode"):
        gym.make_vec("CrispTrack-v0", autoreset_mode="sometimes", **kwargs)


def test_blowing_up_ends_the_episode_with_a_bounded_reward(sway_clip):
    """Random full-scale actions make the humanoid flail: every reward stays finite and above the
    energy term's bound, and an episode whose hinges outrun ``max_joint_speed`` ends as unstable."""
    venv = gym.make_vec("CrispTrack-v0", num_envs=8, vectorization_mode="vector_entry_point", clip=str(sway_clip))
    config = venv.unwrapped.config
    floor = -config.w_energy * config.max_power
    venv.reset(seed=0)
    venv.action_space.seed(0)
    unstable_seen = 0
    for _ in range(60):
        _, reward, terminated, _, info = venv.step(venv.action_space.sample() * 4.0)
        assert np.all(np.isfinite(reward)) and np.all(reward >= floor - 1e-9)
        assert not np.any(info["unstable"] & ~terminated)
        unstable_seen += int(info["unstable"].sum())
    single = gym.make("CrispTrack-v0", clip=str(sway_clip))
    _, info = single.reset(seed=0)
    assert info["unstable"] is False and info["success"] is False and "reward_energy" in info
    data = single.unwrapped.data
    data.qvel[10] = 1e4  # a hinge spinning (as a blowing-up simulation does): the next step ends the episode
    _, reward, terminated, _, info = single.step(np.zeros(single.action_space.shape))
    assert terminated and info["unstable"] and np.isfinite(reward)
    single.close()
    venv.close()


def test_batched_env_renders_every_simulation_as_the_single_env_would(sway_clip):
    """``render_mode="rgb_array"`` on the batched env (it refused to render): one image per
    simulation, each the single env's image of the same state."""
    from crisp_gym.envs.track_vector import CrispTrackVectorEnv

    size = {"render_width": 96, "render_height": 72}
    venv = CrispTrackVectorEnv(3, clip=str(sway_clip), render_mode="rgb_array", **size)
    venv.reset(seed=0, options={"start_frame": [0, 10, 20]})
    venv.step(np.zeros((3, venv.model.nu)))
    images = venv.render()
    single = CrispTrackEnv(clip=str(sway_clip), render_mode="rgb_array", **size)
    single.reset(seed=0)
    assert len(images) == 3 and len({img.tobytes() for img in images}) == 3  # three different poses
    for k, image in enumerate(images):
        single.data.qpos[:], single.data.qvel[:] = venv._fields["qpos"][k], venv._fields["qvel"][k]
        mujoco.mj_forward(single.model, single.data)
        np.testing.assert_array_equal(image, single.render())
    venv.close()
    single.close()


class _RecordingViewer:
    """Stands in for MuJoCo's passive viewer window: records what it was asked to show."""

    def __init__(self, model, data, **kwargs):
        self.data, self.synced, self.closed = data, [], False

    def lock(self):
        return contextlib.nullcontext()

    def sync(self):
        self.synced.append(self.data.qpos.copy())

    def close(self):
        self.closed = True


@pytest.mark.parametrize("batched", [False, True])
def test_human_mode_shows_every_step_in_mujocos_viewer(sway_clip, monkeypatch, batched):
    """``render_mode="human"`` (it needed pygame) opens MuJoCo's own viewer and syncs it on reset
    and every step with the (first) simulation's state; without a display it says so instead of
    letting GLFW end the process."""
    import mujoco.viewer

    from crisp_gym import render
    from crisp_gym.envs.track_vector import CrispTrackVectorEnv

    viewers = []

    def launch_passive(model, data, **kwargs):
        viewers.append(_RecordingViewer(model, data, **kwargs))
        return viewers[-1]

    monkeypatch.setattr(render, "has_display", lambda: True)
    monkeypatch.setattr(mujoco.viewer, "launch_passive", launch_passive)
    env = CrispTrackVectorEnv(2, clip=str(sway_clip), render_mode="human") if batched else \
        CrispTrackEnv(clip=str(sway_clip), render_mode="human")
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.zeros((2, env.model.nu)) if batched else np.zeros(env.model.nu))
    (viewer,) = viewers
    assert len(viewer.synced) == 4  # reset and three steps
    shown = env._fields["qpos"][0] if batched else env.data.qpos
    np.testing.assert_array_equal(viewer.synced[-1], shown)
    env.close()
    assert viewer.closed
    monkeypatch.setattr(render, "has_display", lambda: False)
    headless = CrispTrackEnv(clip=str(sway_clip), render_mode="human")
    with pytest.raises(RuntimeError, match="needs a display"):
        headless.reset(seed=0)
