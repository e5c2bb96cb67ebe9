"""Log format, validation and adapters of the gap tool."""

from pathlib import Path

import numpy as np
import pytest

from crisp_gym.sim2real.log import RealLog, load_log, save_log, validate_against_model
from crisp_gym.sim2real.models import SERVO_ACTUATOR, SERVO_JOINT, build_servo_pendulum
from crisp_gym.sim2real.recorder import LogRecorder

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _log(**kw) -> RealLog:
    t = np.arange(50) * 0.01
    args = dict(time=t, qpos=np.sin(t)[:, None], ctrl=np.sin(t)[:, None], joint_names=(SERVO_JOINT,),
                actuator_names=(SERVO_ACTUATOR,))
    args.update(kw)
    return RealLog(**args)


def test_roundtrip(tmp_path):
    log = _log(meta={"kp": 400})
    back = load_log(save_log(log, tmp_path / "a.npz"))
    np.testing.assert_array_equal(back.qpos, log.qpos)
    assert back.joint_names == log.joint_names and back.meta["kp"] == 400


@pytest.mark.parametrize("kw, message", [
    (dict(time=np.r_[np.arange(49) * 0.01, 0.2]), "increase"),
    (dict(qpos=np.r_[np.zeros(49), np.nan][:, None]), "NaN"),
    (dict(time=np.r_[np.arange(25) * 0.01, 0.3 + np.arange(25) * 0.01]), "uniformly"),
])
def test_bad_arrays_raise(kw, message):
    with pytest.raises(ValueError, match=message):
        _log(**kw)


def test_unknown_name_and_degrees_raise():
    model = build_servo_pendulum()
    with pytest.raises(ValueError, match="not in the model"):
        validate_against_model(_log(joint_names=("elbow",)), model)
    t = np.arange(50) * 0.01
    with pytest.raises(ValueError, match="degrees"):
        validate_against_model(_log(qpos=(90 * np.sin(t))[:, None]), model)


def test_recorder_matches_simulation():
    import mujoco

    model = build_servo_pendulum()
    data = mujoco.MjData(model)
    rec = LogRecorder(model)
    for k in range(40):
        data.ctrl[0] = 0.3
        rec.record(data)
        mujoco.mj_step(model, data)
    log = rec.log()
    assert log.joint_names == (SERVO_JOINT,) and log.qpos.shape == (40, 1)
    assert log.qpos[-1, 0] > 0.05  # the servo moved toward its 0.3 rad command


def test_servo_adapter_reads_torque_off():
    files = sorted((DATA / "bam_xl330").glob("*.json")) if DATA.is_dir() else []
    if not files:
        pytest.skip("real servo logs not available")
    from crisp_gym.sim2real.adapters import load_servo_json

    logs = [load_servo_json(f)[0] for f in files]
    drops = [lg for lg in logs if lg.meta["trajectory"] == "lift_and_drop"]
    assert drops and all(not lg.ctrl_enabled.all() and lg.ctrl_enabled[0, 0] for lg in drops)
    assert sorted({lg.meta["kp"] for lg in logs}) == [100, 200, 400, 800]


def test_go2_adapter_fixed_base_tracks():
    path = DATA / "go2_fixed_base" / "traj_0.npz"
    if not path.is_file():
        pytest.skip("Go2 log not available")
    from crisp_gym.sim2real.adapters import load_go2_npz
    from crisp_gym.sim2real.replay import Replayer, bind, make_windows, nominal_inputs

    tr = bind(*load_go2_npz(path))
    rep = Replayer([tr], make_windows([tr], 0.5))
    q = rep.open_loop(nominal_inputs([tr]))[0]
    # The welded base must not collide with its legs: open loop follows the real log closely.
    assert np.sqrt(np.mean((q - tr.log.qpos) ** 2)) < 0.05


def test_cli_model_gains_an_inert_support_placeholder(tmp_path):
    """``--model`` MJCFs get the parked box the missing-support effect moves into place;
    it must not change the nominal dynamics."""
    import mujoco

    from crisp_gym.sim2real.cli import load_any
    from crisp_gym.sim2real.models import SUPPORT_SLOT, build_humanoid_bench_spec

    spec = build_humanoid_bench_spec()
    spec.delete(spec.body(SUPPORT_SLOT))
    xml = tmp_path / "robot.xml"
    xml.write_text(spec.to_xml())
    plain = mujoco.MjModel.from_xml_path(str(xml))
    t = np.arange(20) * 0.01
    log = RealLog(time=t, qpos=np.zeros((20, 1)), ctrl=np.full((20, 1), 0.3), joint_names=("L_Knee_y",),
                  actuator_names=("L_Knee_y",))
    _, spec = load_any(save_log(log, tmp_path / "log.npz"), xml)
    model = spec.compile()
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, SUPPORT_SLOT) >= 0
    assert mujoco.mj_name2id(plain, mujoco.mjtObj.mjOBJ_GEOM, SUPPORT_SLOT) < 0
    traj = []
    for m in (plain, model):
        d = mujoco.MjData(m)
        d.ctrl[m.actuator("L_Knee_y").id] = 0.3
        for _ in range(200):
            mujoco.mj_step(m, d)
        traj.append(d.qpos.copy())
    np.testing.assert_allclose(traj[0], traj[1], atol=1e-12)


@pytest.mark.parametrize("blocks", [1, 2, 3, 5])
def test_holdout_blocks_partition_the_log_in_time_order(blocks):
    log = _log(time=np.arange(200) * 0.01, qpos=np.zeros((200, 1)), ctrl=np.zeros((200, 1)))
    fitted, held = log.holdout_blocks(0.3, blocks)
    assert len(fitted) == len(held) == blocks
    spans = sorted(part.meta["slice"] for part in fitted + held)
    assert spans[0][0] == 0 and spans[-1][1] == 200
    assert all(a[1] == b[0] for a, b in zip(spans, spans[1:]))  # back to back: no gap, no overlap
    for f, h in zip(fitted, held):  # each block's held-out part follows its fitted part
        assert f.meta["slice"][1] == h.meta["slice"][0]
        assert abs(len(h.time) / (len(f.time) + len(h.time)) - 0.3) <= 1 / (len(f.time) + len(h.time))
    if blocks == 1:
        assert held[0].meta["slice"] == [140, 200]


def test_too_many_holdout_blocks_raise():
    with pytest.raises(ValueError, match="fewer blocks"):
        _log().holdout_blocks(0.3, 4)  # 50 samples: held-out parts of 4 samples
