import mujoco
import numpy as np
import pytest

from crisp_gym.humanoid import (
    BODY_NAMES,
    DEFAULT_MODEL_PATH,
    DOF_NAMES,
    GAIN_GROUPS,
    HumanoidConfig,
    build_humanoid,
    build_humanoid_spec,
    default_rest_joints,
    joint_range_deg,
)


def test_shipped_model_is_what_the_code_generates():
    assert DEFAULT_MODEL_PATH.read_text() == build_humanoid_spec().to_xml()


def test_topology_names_and_order():
    model = build_humanoid()
    assert model.nbody == 25 and model.nu == 69 and model.nq == 7 + 69
    assert [model.body(i).name for i in range(1, 25)] == list(BODY_NAMES)
    hinge_names = [model.joint(j).name for j in range(1, model.njnt)]
    assert hinge_names == list(DOF_NAMES)
    assert [model.actuator(a).name for a in range(model.nu)] == list(DOF_NAMES)
    # depth-first: every body's parent comes before it
    assert all(model.body_parentid[i] < i for i in range(1, model.nbody))


def test_mass_and_height_scale():
    model = build_humanoid()
    assert model.body_subtreemass[1] == pytest.approx(70.0, rel=1e-6)
    tall = build_humanoid(HumanoidConfig(height=1.90))
    assert tall.body_subtreemass[1] == pytest.approx(70.0 * (1.90 / 1.70) ** 3, rel=1e-6)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    top = max(data.geom_xpos[g, 2] + model.geom_rbound[g] for g in range(model.ngeom)
              if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE)
    assert top == pytest.approx(1.70, abs=0.03)  # head top near the stature
    lowest = min(data.geom_xpos[g, 2] - model.geom_size[g, 2] for g in range(model.ngeom)
                 if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX and model.body(model.geom_bodyid[g]).name
                 in ("L_Ankle", "R_Ankle"))
    assert lowest == pytest.approx(0.0, abs=1e-9)  # soles on the floor in the rest pose


def test_gains_and_ranges():
    model = build_humanoid()
    knee = model.actuator("L_Knee_y")
    assert knee.gainprm[0] == GAIN_GROUPS["legs"].kp and model.actuator_damping[knee.id] == GAIN_GROUPS["legs"].kd
    assert knee.biasprm[2] == 0.0 and knee.forcerange[1] == GAIN_GROUPS["legs"].torque_limit
    inside_model = build_humanoid(HumanoidConfig(passive_damping=False))
    inside = inside_model.actuator("L_Knee_y")
    assert inside.biasprm[2] == -GAIN_GROUPS["legs"].kd and inside_model.actuator_damping[inside.id] == 0.0
    assert model.actuator("Spine_x").gainprm[0] == 1000.0
    assert model.actuator("L_Elbow_z").gainprm[0] == 500.0
    assert model.actuator("R_Wrist_y").gainprm[0] == 300.0
    # knee flexes positively about y, hips flex negatively; right side mirrors the x and z ranges
    assert joint_range_deg("L_Knee")[1, 1] > 120 and joint_range_deg("L_Hip")[1, 0] < -100
    np.testing.assert_allclose(joint_range_deg("R_Hip")[0], -joint_range_deg("L_Hip")[0][::-1])
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    assert model.opt.timestep == pytest.approx(1 / 120)


def test_user_rest_joints_are_used():
    rest = default_rest_joints(1.70)
    rest[BODY_NAMES.index("L_Elbow")] += [0, 0.05, 0]  # a longer upper arm
    model = build_humanoid(HumanoidConfig(rest_joints=rest))
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    upper_arm = data.xpos[model.body("L_Elbow").id] - data.xpos[model.body("L_Shoulder").id]
    assert np.linalg.norm(upper_arm) == pytest.approx(0.186 * 1.70 + 0.05, abs=1e-9)
    with pytest.raises(ValueError, match="shape"):
        build_humanoid(HumanoidConfig(rest_joints=np.zeros((23, 3))))
    with pytest.raises(ValueError, match="stature"):
        default_rest_joints(7.0)


def _on_floor(config: HumanoidConfig) -> mujoco.MjModel:
    spec = build_humanoid_spec(config)
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=(5, 5, 0.1), contype=1, conaffinity=2)
    return spec.compile()


def test_pd_holds_the_rest_pose_on_a_floor():
    model = _on_floor(HumanoidConfig())
    data = mujoco.MjData(model)
    data.qpos[2] += 0.002
    for _ in range(240):  # 2 s
        mujoco.mj_step(model, data)
    assert np.all(np.isfinite(data.qpos)) and not any(w.number for w in data.warning)
    assert data.qpos[2] > 0.9  # still standing


def _servo_torque(model: mujoco.MjModel, data: mujoco.MjData, joint: str) -> float:
    return float(data.actuator_force[model.actuator(joint).id] + data.qfrc_damper[model.joint(joint).dofadr[0]])


@pytest.mark.parametrize("passive", [True, False])
def test_servo_torque_is_the_pd_law_below_its_limit(passive):
    """Below the torque limit, damping inside the servo or passive at the hinge is the same
    torque kp (target - q) - kd qdot (a known answer from the gain table)."""
    model = build_humanoid(HumanoidConfig(passive_damping=passive))
    data = mujoco.MjData(model)
    group = GAIN_GROUPS["legs"]
    data.qpos[model.joint("L_Knee_y").qposadr[0]] = 0.3
    data.qvel[model.joint("L_Knee_y").dofadr[0]] = 1.5
    data.ctrl[model.actuator("L_Knee_y").id] = 0.4
    mujoco.mj_forward(model, data)
    assert _servo_torque(model, data, "L_Knee_y") == pytest.approx(group.kp * 0.1 - group.kd * 1.5)


def _largest_hinge_speed(model: mujoco.MjModel, seconds: float, sigma: float, seed: int) -> float:
    """Stand the humanoid on a floor and drive every servo with targets ``sigma`` rad off its rest
    pose, redrawn at 30 Hz: far enough that hands, wrists and toes saturate."""
    rng = np.random.default_rng(seed)
    data = mujoco.MjData(model)
    fastest = 0.0
    for step in range(int(seconds / model.opt.timestep)):
        if step % 4 == 0:
            data.ctrl[:] = rng.normal(0.0, sigma, model.nu)
        mujoco.mj_step(model, data)
        speed = np.abs(data.qvel[6:]).max()
        fastest = max(fastest, speed if np.isfinite(speed) else np.inf)
    return fastest


def test_saturated_servos_stay_stable_with_passive_damping():
    """Saturated servos on light bodies: with the damping inside the clamp they turn explicitly
    and blow up (the model's old form, checked so the test can fail); with passive damping no
    hinge comes near a person's ~30 rad/s."""
    assert _largest_hinge_speed(_on_floor(HumanoidConfig(passive_damping=False)), 1.0, 0.5, 0) > 100.0
    assert _largest_hinge_speed(_on_floor(HumanoidConfig()), 1.0, 0.5, 0) < 40.0
