"""The vectorised tracking functions against straightforward per-body references.

The expectations are written independently of :mod:`crisp_gym.envs.quat`: rotations through
``scipy.spatial.transform.Rotation`` and one body at a time, following the definitions in the
docstring of :mod:`crisp_gym.envs.tracking` (heading frame = the root's yaw; rotation features
= the rotated x and z axes, i.e. matrix columns 0 and 2).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crisp_gym.envs import quat, tracking
from crisp_gym.envs.config import TrackConfig
from crisp_gym.envs.tracking import NUM_BODIES, PROPRIO_DIM, TARGET_DIM, Reference, SimState

N, T, K = 5, 12, 3
B = NUM_BODIES
TOL = dict(rtol=1e-12, atol=1e-12)


def _unit_quats(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)  # both signs of w, as MuJoCo's can have


def _rot(q: np.ndarray) -> Rotation:
    return Rotation.from_quat(q, scalar_first=True)


def _axes(r: Rotation) -> np.ndarray:
    """(6,) the rotated x and z axes."""
    m = r.as_matrix()
    return np.concatenate([m[:, 0], m[:, 2]])


def _heading(root_quat: np.ndarray) -> Rotation:
    """The inverse of the root's heading: minus the yaw of its rotated x axis, about +z."""
    x_axis = _rot(root_quat).as_matrix()[:, 0]
    return Rotation.from_euler("z", -np.arctan2(x_axis[1], x_axis[0]))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


@pytest.fixture
def state(rng) -> SimState:
    return SimState(qpos=rng.normal(size=(N, 76)), qvel=rng.normal(size=(N, 75)),
                    body_pos=rng.normal(0.0, 2.0, (N, B, 3)) + [3.0, -1.0, 0.9],
                    body_quat=_unit_quats(rng, (N, B)), body_lin_vel=rng.normal(0.0, 3.0, (N, B, 3)),
                    body_ang_vel=rng.normal(0.0, 5.0, (N, B, 3)), servo_torque=rng.normal(0.0, 50.0, (N, 69)))


@pytest.fixture
def ref(rng) -> Reference:
    return Reference(qpos=rng.normal(size=(T, 76)), qvel=rng.normal(size=(T, 75)),
                     body_pos=rng.normal(0.0, 2.0, (T, B, 3)) + [3.2, -0.8, 0.9], body_quat=_unit_quats(rng, (T, B)),
                     body_lin_vel=rng.normal(0.0, 3.0, (T, B, 3)), body_ang_vel=rng.normal(0.0, 5.0, (T, B, 3)))


def test_quat_matrices_match_scipy(rng):
    q = _unit_quats(rng, (7, 11))
    expected = _rot(q.reshape(-1, 4)).as_matrix().reshape(7, 11, 3, 3)
    np.testing.assert_allclose(quat.matrix(q), expected, **TOL)
    np.testing.assert_allclose(quat.tangent_normal(q),
                               np.concatenate([expected[..., :, 0], expected[..., :, 2]], axis=-1), **TOL)
    pair = quat.matrix_pair(q)
    np.testing.assert_allclose(pair[..., :3, :3], expected, **TOL)
    np.testing.assert_allclose(pair[..., 3:, 3:], expected, **TOL)
    assert not pair[..., :3, 3:].any() and not pair[..., 3:, :3].any()


def test_quat_heading_and_cross_match_scipy(rng):
    q = _unit_quats(rng, (9,))
    v = rng.normal(size=(9, 3))
    expected = np.stack([_heading(qi).apply(vi) for qi, vi in zip(q, v)])
    np.testing.assert_allclose((v[:, None] @ quat.inverse_yaw_matrix(quat.yaw(q)))[:, 0], expected, **TOL)
    np.testing.assert_allclose(quat.rotate(tracking._heading_inverse(q)[:, 0], v), expected, **TOL)
    np.testing.assert_allclose(quat.cross(v, v[::-1]), np.cross(v, v[::-1]), **TOL)


def test_sim_state_reads_the_bodies_and_moves_velocities_to_their_origins(rng):
    nbody = B + 3  # the world first and a scene body after the humanoid, as in a composed model
    body_ids = np.arange(1, B + 1)
    xpos, xquat = rng.normal(size=(N, nbody, 3)), _unit_quats(rng, (N, nbody))
    cvel, com = rng.normal(size=(N, nbody, 6)), rng.normal(size=(N, nbody, 3))
    qpos, qvel, force = rng.normal(size=(N, 76)), rng.normal(size=(N, 75)), rng.normal(size=(N, 69))
    damper = np.concatenate([np.zeros((N, 6)), rng.normal(size=(N, 69))], axis=1)
    s = tracking.sim_state(qpos, qvel, xpos, xquat, cvel, com, force, damper, body_ids)
    for n in range(N):
        for b, body in enumerate(body_ids):
            omega, v = cvel[n, body, :3], cvel[n, body, 3:]
            np.testing.assert_allclose(s.body_lin_vel[n, b], v + np.cross(omega, xpos[n, body] - com[n, 1]), **TOL)
            np.testing.assert_array_equal(s.body_ang_vel[n, b], omega)
            np.testing.assert_array_equal(s.body_pos[n, b], xpos[n, body])
            np.testing.assert_array_equal(s.body_quat[n, b], xquat[n, body])
    assert s.qpos is qpos and s.qvel is qvel
    np.testing.assert_array_equal(s.servo_torque, force + damper[:, 6:])


def test_proprioception_matches_per_body_reference(state):
    got = tracking.proprioception(state)
    assert got.shape == (N, PROPRIO_DIM)
    for n in range(N):
        heading = _heading(state.body_quat[n, 0])
        root = state.body_pos[n, 0]
        rel_pos = [heading.apply(state.body_pos[n, b] - root) for b in range(B)]
        rot = [_axes(heading * _rot(state.body_quat[n, b])) for b in range(B)]
        lin = [heading.apply(state.body_lin_vel[n, b]) for b in range(B)]
        ang = [heading.apply(state.body_ang_vel[n, b]) for b in range(B)]
        expected = np.concatenate([[root[2]], *rel_pos, *rot, *lin, *ang])
        np.testing.assert_allclose(got[n], expected, **TOL)


def test_target_features_match_per_body_reference(state, ref, rng):
    frames = np.sort(rng.integers(0, T, (N, K)), axis=1)
    got = tracking.target_features(state, ref, frames)
    assert got.shape == (N, K, TARGET_DIM)
    for n in range(N):
        heading = _heading(state.body_quat[n, 0])
        for j, frame in enumerate(frames[n]):
            expected = []
            for b in range(B):
                sim_rot, ref_rot = _rot(state.body_quat[n, b]), _rot(ref.body_quat[frame, b])
                expected += [_axes(sim_rot.inv() * ref_rot), _axes(heading * ref_rot),
                             heading.apply(ref.body_pos[frame, b] - state.body_pos[n, b]),
                             heading.apply(ref.body_pos[frame, b] - state.body_pos[n, 0])]
            np.testing.assert_allclose(got[n, j], np.concatenate(expected), **TOL)


def test_target_features_follow_a_replaced_reference(state, ref, rng):
    """The reference axes are derived once from body_quat: a Reference with other rotations gets its own."""
    frames = rng.integers(0, T, (N, K))
    first = tracking.target_features(state, ref, frames)
    np.testing.assert_array_equal(tracking.target_features(state, ref, frames), first)
    other = dataclasses.replace(ref, body_quat=_unit_quats(rng, (T, B)))
    fresh = tracking.target_features(state, dataclasses.replace(other), frames)
    np.testing.assert_array_equal(tracking.target_features(state, other, frames), fresh)
    assert not np.allclose(fresh[..., :12], first[..., :12])
    np.testing.assert_array_equal(fresh.reshape(N, K, B, 18)[..., 12:], first.reshape(N, K, B, 18)[..., 12:])


def test_reward_terms_and_errors_match_per_body_reference(state, ref, rng):
    cfg = TrackConfig()
    frame = rng.integers(0, T, N)
    # one env exactly on its reference (zero errors, rot's arccos at 1)
    state.body_pos[0], state.body_quat[0] = ref.body_pos[frame[0]], ref.body_quat[frame[0]]
    state.body_lin_vel[0], state.body_ang_vel[0] = ref.body_lin_vel[frame[0]], ref.body_ang_vel[frame[0]]
    got = tracking.reward_terms(state, ref, frame, cfg)
    assert set(got) == set(tracking.REWARD_TERMS)
    for n, f in enumerate(frame):
        dist = [np.linalg.norm(ref.body_pos[f, b] - state.body_pos[n, b]) for b in range(B)]
        errors = {
            "pos": sum(dist),
            "rot": sum((_rot(ref.body_quat[f, b]) * _rot(state.body_quat[n, b]).inv()).magnitude() for b in range(B)),
            "vel": sum(np.linalg.norm(ref.body_lin_vel[f, b] - state.body_lin_vel[n, b]) for b in range(B)),
            "ang_vel": sum(np.linalg.norm(ref.body_ang_vel[f, b] - state.body_ang_vel[n, b]) for b in range(B)),
            "height": abs(ref.body_pos[f, 0, 2] - state.body_pos[n, 0, 2]),
        }
        for term, error in errors.items():
            weight, sharpness = getattr(cfg, f"w_{term}"), getattr(cfg, f"a_{term}")
            # the rotation angle of (almost) equal unit quaternions comes through arccos near 1
            tol = dict(rtol=1e-6, atol=0) if n == 0 and term == "rot" else TOL
            np.testing.assert_allclose(got[term][n], weight * np.exp(-sharpness * error), **tol)
        power = sum(abs(state.servo_torque[n, i] * state.qvel[n, 6 + i]) for i in range(69))
        np.testing.assert_allclose(got["energy"][n], -cfg.w_energy * power, **TOL)
        farthest_error, farthest = tracking.farthest_body(state, ref, frame)
        np.testing.assert_allclose(farthest_error[n], max(dist), **TOL)
        assert n == 0 or farthest[n] == int(np.argmax(dist))  # (all zero on the reference)
    assert tracking.farthest_body(state, ref, frame)[0][0] == 0.0


def test_the_root_position_term_still_pulls_a_drifted_body_back(state, ref, rng):
    """Off by default (the paper's six terms). Weighted, it is w·exp(-a·|pelvis error|); with every
    body shifted by the same drift, the summed position term is spent by 0.2 m (under 0.1 % of its
    weight) while this one keeps over half of it."""
    frame = rng.integers(0, T, N)
    assert "root_pos" not in tracking.reward_terms(state, ref, frame, TrackConfig())
    cfg = TrackConfig(w_root_pos=2.0, a_root_pos=3.0)
    got = tracking.reward_terms(state, ref, frame, cfg)
    assert set(got) == set(tracking.reward_term_names(cfg)) == {*tracking.REWARD_TERMS, "root_pos"}
    expected = [2.0 * np.exp(-3.0 * np.linalg.norm(ref.body_pos[f, 0] - state.body_pos[n, 0]))
                for n, f in enumerate(frame)]
    np.testing.assert_allclose(got["root_pos"], expected, **TOL)
    drifts = np.array([0.0, 0.1, 0.2, 0.3])
    for n, drift in enumerate(drifts):  # the reference pose, every body moved sideways by the drift
        state.body_pos[n] = ref.body_pos[frame[n]] + [drift, 0.0, 0.0]
    drifted = tracking.reward_terms(state, ref, frame, cfg)
    pos, root = drifted["pos"][:4] / cfg.w_pos, drifted["root_pos"][:4] / cfg.w_root_pos
    assert np.all(np.diff(root) < 0) and pos[2] < 1e-3 < 0.5 < root[2]
    with pytest.raises(ValueError, match="w_root_pos"):
        TrackConfig(w_root_pos=-1.0)


@pytest.mark.parametrize("residual", [True, False])
def test_pd_targets(ref, rng, residual):
    cfg = TrackConfig(residual_actions=residual, action_scale=0.4)
    ranges = np.sort(rng.uniform(-2.0, 2.0, (69, 2)), axis=1)
    action = rng.uniform(-1.5, 1.5, (N, 69))
    frame = rng.integers(0, T, N)
    got = tracking.pd_targets(action, ref, frame, cfg, ranges)
    clipped = np.clip(action, -1.0, 1.0)
    for n in range(N):
        if residual:
            expected = ref.qpos[frame[n], 7:] + 0.4 * clipped[n]
        else:
            expected = ranges[:, 0] + (clipped[n] + 1.0) / 2.0 * (ranges[:, 1] - ranges[:, 0])
        np.testing.assert_allclose(got[n], expected, **TOL)
    assert np.abs(action).max() > 1.0  # the input is left as it was


def test_pd_targets_velocity_feedforward(ref, rng):
    cfg = TrackConfig(action_scale=0.4, velocity_feedforward=True, max_feedforward_lead=1e6)
    lead = rng.uniform(0.05, 0.2, 69)
    action = rng.uniform(-1.0, 1.0, (N, 69))
    frame = rng.integers(0, T, N)
    got = tracking.pd_targets(action, ref, frame, cfg, np.zeros((69, 2)), lead)
    plain = tracking.pd_targets(action, ref, frame, dataclasses.replace(cfg, velocity_feedforward=False), None)
    for n in range(N):
        np.testing.assert_allclose(got[n] - plain[n], lead * ref.qvel[frame[n], 6:], **TOL)
    with pytest.raises(ValueError, match="damping lead"):
        tracking.pd_targets(action, ref, frame, cfg, np.zeros((69, 2)))


def test_pd_targets_feedforward_lead_is_clipped(ref, rng):
    """Each hinge's lead is its unclipped lead limited to ±max_feedforward_lead: equal where it
    is smaller, the limit with the lead's sign where it is larger."""
    limit = 0.05
    cfg = TrackConfig(velocity_feedforward=True, max_feedforward_lead=limit)
    lead = rng.uniform(0.05, 0.2, 69)
    action = rng.uniform(-1.0, 1.0, (N, 69))
    frame = rng.integers(0, T, N)
    led = tracking.pd_targets(action, ref, frame, cfg, np.zeros((69, 2)), lead) - \
        tracking.pd_targets(action, ref, frame, dataclasses.replace(cfg, velocity_feedforward=False), None)
    free = lead * ref.qvel[frame, 6:]
    small = np.abs(free) <= limit
    assert small.any() and (~small).any()  # the draw exercises both sides of the limit
    np.testing.assert_allclose(led[small], free[small], **TOL)
    np.testing.assert_allclose(led[~small], limit * np.sign(free[~small]), **TOL)
    with pytest.raises(ValueError, match="max_feedforward_lead"):
        TrackConfig(max_feedforward_lead=0.0)


@pytest.mark.parametrize("damping", ['kv="30"', 'damping="30"'])
def test_damping_lead_cancels_a_servos_lag(damping):
    """A position servo following a target that moves at constant speed lags it by kd/kp times
    the speed, whether it damps inside its force (kv) or passively (damping); the target led by
    damping_lead times the speed is followed without lag."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(f"""
    <mujoco><option timestep="0.001" integrator="implicitfast" gravity="0 0 0"/>
      <worldbody><body><joint name="j" axis="0 0 1" armature="0.05"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/></body></worldbody>
      <actuator><position joint="j" kp="200" {damping}/></actuator></mujoco>""")
    lead = tracking.damping_lead(model)
    np.testing.assert_allclose(lead, [30 / 200])
    speed = 2.0
    for feedforward, expected_lag in ((False, lead[0] * speed), (True, 0.0)):
        data = mujoco.MjData(model)
        for _ in range(3000):  # 3 s: the transient of this servo dies out in well under 1 s
            data.ctrl[0] = speed * data.time + (lead[0] * speed if feedforward else 0.0)
            mujoco.mj_step(model, data)
        assert abs(speed * data.time - data.qpos[0] - expected_lag) < 2e-3
