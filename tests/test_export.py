"""``crisp_gym.export``: every format loads in its target library and reproduces its source.

Clip formats are exported once per bundled clip (a module fixture) and each test reads them back
with an independent library: MuJoCo, dm_control, yourdfpy (and MuJoCo's URDF parser), trimesh,
:func:`crisp_gym.smpl.load_smpl_params`, onnxruntime.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
import trimesh
import yourdfpy
from scipy.spatial.transform import Rotation

from crisp_gym.clip import write_clip
from crisp_gym.envs.tracking import build_track_model
from crisp_gym.export import CLIP_FORMATS, ExportConfig, export, export_clip, main
from crisp_gym.export.meshes import write_scene_mesh
from crisp_gym.export.mjcf import mjx_check
from crisp_gym.export.motion_formats import (
    QUAT_ORDERS,
    read_motion_csv,
    read_motion_npz,
    write_motion_csv,
    write_motion_npz,
)
from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, build_humanoid
from crisp_gym.motion import compute_kinematics
from crisp_gym.registry import load_clip
from crisp_gym.scene import load_scene_xml
from crisp_gym.smpl import SMPL_JOINT_NAMES, load_smpl_params

CLIPS = ("flat_walk", "stairs_up", "stairs_down", "platform_step", "chair_sit")
GEOMETRY_TOL = 1e-6  # m
STEPS = 100


@pytest.fixture(scope="module", params=CLIPS)
def exported(request, tmp_path_factory):
    """(clip, output folder) with every clip format written."""
    clip = load_clip(request.param)
    out = tmp_path_factory.mktemp(f"export_{request.param}")
    files = export_clip(clip, out, CLIP_FORMATS)
    assert all(f.is_file() for f in files)
    return clip, out


def _box_names(boxes) -> list[str]:
    return [b.name or f"scene_{i}" for i, b in enumerate(boxes)]


def _assert_boxes_equal(loaded, source) -> None:
    assert [b.name for b in loaded] == _box_names(source)
    for a, b in zip(loaded, source):
        assert np.abs(a.center - b.center).max() < GEOMETRY_TOL
        assert np.abs(a.half_size - b.half_size).max() < GEOMETRY_TOL
        assert np.abs(a.rotation - b.rotation).max() < 1e-9


def _rollout(model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, targets: np.ndarray) -> tuple:
    """``STEPS`` physics steps from (qpos, qvel), holding each PD target for 4 substeps; final state, contacts."""
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = qpos, qvel
    contacts = 0
    for i in range(STEPS):
        data.ctrl[:] = targets[i // 4]
        mujoco.mj_step(model, data)
        contacts += data.ncon
    return data.qpos.copy(), data.qvel.copy(), contacts


def _targets(clip, start: int) -> np.ndarray:
    """PD targets for the rollouts: the reference pose plus noise (a fixed seed for both models)."""
    dof = clip.motion.dof_pos
    frames = np.minimum(start + 1 + np.arange(STEPS // 4 + 1), len(dof) - 1)
    return dof[frames] + 0.05 * np.random.default_rng(0).standard_normal((len(frames), dof.shape[1]))


# ------------------------------------------------------------------------------------------------
# MJCF


def test_scene_mjcf_round_trips(exported) -> None:
    clip, out = exported
    _assert_boxes_equal(load_scene_xml(out / "mjcf" / "scene.xml"), clip.boxes)
    _assert_boxes_equal(load_scene_xml(out / "mjcf" / "track.xml"), clip.boxes)
    model = mujoco.MjModel.from_xml_path(str(out / "mjcf" / "scene.xml"))
    np.testing.assert_array_equal(model.geom_friction, np.tile([1.0, 0.005, 0.0001], (model.ngeom, 1)))


def test_track_mjcf_steps_like_the_env(exported) -> None:
    """Same state after 100 steps with the same controls as the env's own model, from a keyframe."""
    clip, out = exported
    exported_model = mujoco.MjModel.from_xml_path(str(out / "mjcf" / "track.xml"))
    original = build_track_model(clip.boxes, 1.0 / 120.0)
    motion = clip.motion
    assert exported_model.nkey == motion.num_frames
    np.testing.assert_allclose(exported_model.key_qpos, motion.qpos(), atol=1e-12)
    np.testing.assert_allclose(exported_model.key_ctrl, motion.dof_pos, atol=1e-12)
    start = motion.num_frames // 2
    data = mujoco.MjData(exported_model)
    mujoco.mj_resetDataKeyframe(exported_model, data, start)
    targets = _targets(clip, start)
    q_a, v_a, contacts = _rollout(exported_model, data.qpos, data.qvel, targets)
    q_b, v_b, _ = _rollout(original, motion.qpos()[start], motion.qvel()[start], targets)
    assert contacts > 0  # the humanoid stands on the scene: contacts are part of what must agree
    assert np.abs(q_a - q_b).max() <= 1e-9 and np.abs(v_a - v_b).max() <= 1e-9


def test_mjx_profile(exported) -> None:
    clip, out = exported
    model = mujoco.MjModel.from_xml_path(str(out / "mjx" / "track.xml"))
    floor = model.geom("floor").id
    assert mujoco.mjtGeom(int(model.geom_type[floor])) == mujoco.mjtGeom.mjGEOM_PLANE
    floor_box = next(b for b in clip.boxes if b.name == "floor")
    assert abs(model.geom_pos[floor, 2] - floor_box.top_height()) < GEOMETRY_TOL
    others = [b for b in clip.boxes if b.name != "floor"]
    _assert_boxes_equal([b for b in load_scene_xml(out / "mjx" / "scene.xml")], others)
    pytest.importorskip("mujoco.mjx")
    assert mjx_check(model)


def test_dm_control_profile_composes_to_the_env_model(exported) -> None:
    from dm_control import mjcf

    clip, out = exported
    folder = out / "dm_control"
    assert mjcf.from_path(str(folder / "track.xml")).find("body", "Pelvis") is not None
    arena = mjcf.from_path(str(folder / "arena.xml"))
    arena.attach(mjcf.from_path(str(folder / "walker.xml"))).add("freejoint")
    composed = mujoco.MjModel.from_xml_string(arena.to_xml_string(), arena.get_assets())
    _assert_boxes_equal(load_scene_xml(folder / "arena.xml"), clip.boxes)
    original = build_track_model(clip.boxes, 1.0 / 120.0)
    start = clip.motion.num_frames // 3
    targets = _targets(clip, start)
    qpos, qvel = clip.motion.qpos()[start], clip.motion.qvel()[start]
    q_a, v_a, _ = _rollout(composed, qpos, qvel, targets)
    q_b, v_b, _ = _rollout(original, qpos, qvel, targets)
    assert np.abs(q_a - q_b).max() <= 1e-9 and np.abs(v_a - v_b).max() <= 1e-9


@pytest.mark.slow
def test_mjx_steps_close_to_mujoco() -> None:
    """MJX follows MuJoCo over 4 steps of the mjx profile (JAX on CPU: minutes to compile).

    Not exactly: MJX runs in float32 with its own collision and solver code (measured 1.1e-3 here).
    """
    jax = pytest.importorskip("jax")
    from mujoco import mjx

    from crisp_gym.export.mjcf import floor_to_plane, track_spec

    clip = load_clip("flat_walk")
    spec = track_spec(clip)
    floor_to_plane(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 10)
    mx = mjx.put_model(model)
    dx = mjx.make_data(mx).replace(qpos=jax.numpy.array(data.qpos), qvel=jax.numpy.array(data.qvel),
                                   ctrl=jax.numpy.array(model.key_ctrl[11]))
    data.ctrl[:] = model.key_ctrl[11]
    step = jax.jit(mjx.step)
    for _ in range(4):
        dx = step(mx, dx)
        mujoco.mj_step(model, data)
    assert np.abs(np.asarray(dx.qpos) - data.qpos).max() < 5e-3


# ------------------------------------------------------------------------------------------------
# URDF


def test_scene_urdf_boxes(exported) -> None:
    clip, out = exported
    urdf = yourdfpy.URDF.load(str(out / "urdf" / "scene.urdf"))
    (link,) = urdf.robot.links
    assert [c.name for c in link.collisions] == _box_names(clip.boxes) == [v.name for v in link.visuals]
    for collision, box in zip(link.collisions, clip.boxes):
        assert np.abs(collision.origin[:3, 3] - box.center).max() < GEOMETRY_TOL
        assert np.abs(collision.origin[:3, :3] - box.rotation).max() < 1e-9
        assert np.abs(collision.geometry.box.size - 2 * box.half_size).max() < GEOMETRY_TOL
    # a second parser: MuJoCo's URDF importer puts the fixed root link's boxes in the world
    _assert_boxes_equal(load_scene_xml(out / "urdf" / "scene.urdf"), clip.boxes)


@pytest.fixture(scope="module")
def humanoid_urdf(tmp_path_factory) -> Path:
    from crisp_gym.export.urdf import write_urdf

    return write_urdf(load_clip("flat_walk").boxes, tmp_path_factory.mktemp("urdf"))[1]


def _mujoco_pose(frame: int) -> tuple[mujoco.MjModel, mujoco.MjData, np.ndarray]:
    """The humanoid in a posture of chair_sit with the pelvis at the origin, unrotated."""
    model, motion = build_humanoid(), load_clip("chair_sit").motion
    data = mujoco.MjData(model)
    data.qpos[7:] = motion.dof_pos[frame]
    data.qpos[3] = 1.0
    mujoco.mj_kinematics(model, data)
    return model, data, motion.dof_pos[frame]


@pytest.mark.parametrize("frame", [0, 70])
def test_humanoid_urdf_kinematics_and_geometry(humanoid_urdf: Path, frame: int) -> None:
    model, data, hinges = _mujoco_pose(frame)
    urdf = yourdfpy.URDF.load(str(humanoid_urdf))
    assert sorted(urdf.actuated_joint_names) == sorted(DOF_NAMES)
    urdf.update_cfg(dict(zip(DOF_NAMES, hinges)))
    pelvis = data.xpos[model.body("Pelvis").id]
    links = {link.name: link for link in urdf.robot.links}
    for body in BODY_NAMES:
        b = model.body(body).id
        transform = urdf.get_transform(body, "Pelvis")
        assert np.abs(transform[:3, 3] - (data.xpos[b] - pelvis)).max() < GEOMETRY_TOL
        assert np.abs(transform[:3, :3] - data.xmat[b].reshape(3, 3)).max() < 1e-9
        # every MuJoCo geom reappears at the same place; a capsule as a cylinder plus end spheres
        collisions = {c.name: c for c in links[body].collisions}
        for i in range(model.body_geomnum[b]):
            g = model.body_geomadr[b] + i
            part = collisions[f"{body}_geom{i}"]
            world = transform @ part.origin
            assert np.abs(world[:3, 3] - (data.geom_xpos[g] - pelvis)).max() < GEOMETRY_TOL
            axis = data.geom_xmat[g].reshape(3, 3)[:, 2]
            size, kind = model.geom_size[g], mujoco.mjtGeom(int(model.geom_type[g]))
            if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
                assert abs(part.geometry.cylinder.radius - size[0]) < GEOMETRY_TOL
                assert abs(part.geometry.cylinder.length - 2 * size[1]) < GEOMETRY_TOL
                for end, sign in (("cap0", -1), ("cap1", 1)):
                    centre = (transform @ collisions[f"{body}_geom{i}_{end}"].origin)[:3, 3]
                    expected = data.geom_xpos[g] + sign * size[1] * axis - pelvis
                    assert np.abs(centre - expected).max() < GEOMETRY_TOL
            elif kind == mujoco.mjtGeom.mjGEOM_BOX:
                assert np.abs(part.geometry.box.size - 2 * size).max() < GEOMETRY_TOL
                assert np.abs(world[:3, :3] - data.geom_xmat[g].reshape(3, 3)).max() < 1e-9
            else:
                assert abs(part.geometry.sphere.radius - size[0]) < GEOMETRY_TOL


def test_humanoid_urdf_in_mujoco_and_actuators(humanoid_urdf: Path) -> None:
    """MuJoCo's own URDF parser (root link fixed at the origin) gives the same body poses."""
    model, data, hinges = _mujoco_pose(70)
    from_urdf = mujoco.MjModel.from_xml_path(str(humanoid_urdf))
    urdf_data = mujoco.MjData(from_urdf)
    for name, angle in zip(DOF_NAMES, hinges):
        urdf_data.qpos[from_urdf.jnt_qposadr[from_urdf.joint(name).id]] = angle
    mujoco.mj_kinematics(from_urdf, urdf_data)
    pelvis = data.xpos[model.body("Pelvis").id]
    for body in BODY_NAMES[1:]:
        got = urdf_data.xpos[from_urdf.body(body).id]
        assert np.abs(got - (data.xpos[model.body(body).id] - pelvis)).max() < GEOMETRY_TOL
        np.testing.assert_allclose(from_urdf.body_mass[from_urdf.body(body).id], model.body_mass[model.body(body).id])
    table = json.loads((humanoid_urdf.parent / "humanoid_actuators.json").read_text())["joints"]
    assert set(table) == set(DOF_NAMES)
    # the design's group gains: legs 800/80, spine 1000/100, arms 500/50, hands 300/30
    for joint, (kp, kd) in {"L_Knee_y": (800, 80), "Spine_x": (1000, 100), "R_Elbow_z": (500, 50),
                            "L_Wrist_y": (300, 30)}.items():
        assert (table[joint]["kp"], table[joint]["kd"]) == (kp, kd)
        assert urdf_limit(humanoid_urdf, joint) == pytest.approx(
            (table[joint]["lower"], table[joint]["upper"], table[joint]["effort_limit"]))


def urdf_limit(path: Path, joint: str) -> tuple[float, float, float]:
    limit = next(j for j in yourdfpy.URDF.load(str(path)).robot.joints if j.name == joint).limit
    return limit.lower, limit.upper, limit.effort


# ------------------------------------------------------------------------------------------------
# Meshes


@pytest.mark.parametrize("kind", ["glb", "obj"])
def test_scene_meshes(exported, kind: str) -> None:
    clip, out = exported
    scene = trimesh.load(out / "mesh" / f"scene.{kind}", force="scene", split_objects=True, group_material=False)
    assert sorted(scene.graph.nodes_geometry) == sorted(_box_names(clip.boxes))
    for name, box in zip(_box_names(clip.boxes), clip.boxes):
        transform, geometry = scene.graph[name]
        vertices = trimesh.transform_points(scene.geometry[geometry].vertices, transform)
        corners = box.corners()
        # each vertex is a corner and each corner a vertex
        distances = np.linalg.norm(vertices[:, None] - corners[None], axis=-1)
        assert distances.min(axis=1).max() < GEOMETRY_TOL and distances.min(axis=0).max() < GEOMETRY_TOL
    if kind == "obj":  # as a user loads it, with no options: one geometry per box, named like it
        loaded = trimesh.load(out / "mesh" / "scene.obj", force="scene")
        assert sorted(loaded.geometry) == sorted(_box_names(clip.boxes))


def test_meshes_colour_by_source(tmp_path: Path) -> None:
    from crisp_gym.scene import Box, floor_box

    boxes = [floor_box(), Box(center=[1, 0, 0.2], half_size=[0.2, 0.2, 0.2], source="contact", name="support")]
    path = write_scene_mesh(boxes, tmp_path / "scene.glb", color_by_source=True)
    scene = trimesh.load(path, force="scene")
    colours = {name: tuple(scene.geometry[scene.graph[name][1]].visual.face_colors[0]) for name in ("floor", "support")}
    assert colours["floor"] != colours["support"]
    with pytest.raises(ValueError, match="end in"):
        write_scene_mesh(boxes, tmp_path / "scene.stl")


# ------------------------------------------------------------------------------------------------
# Motion


@pytest.mark.parametrize("quat_order", QUAT_ORDERS)
def test_motion_csv_and_npz_round_trip(exported, quat_order: str, tmp_path: Path) -> None:
    clip, _ = exported
    motion = clip.motion
    path = write_motion_csv(motion, tmp_path / "motion.csv", quat_order)
    with open(path, newline="") as f:
        header, first = next(csv.reader(f)), next(csv.reader(f))
    quat = [float(first[header.index(f"root_quat_{c}")]) for c in quat_order]
    assert header[5:9] == [f"root_quat_{c}" for c in quat_order]
    np.testing.assert_array_equal(quat, motion.root_quat[0] if quat_order == "wxyz" else np.roll(motion.root_quat[0], -1))
    loaded = [read_motion_csv(path)]
    for layout in ("fields", "qpos"):
        loaded.append(read_motion_npz(write_motion_npz(motion, tmp_path / f"{layout}.npz", layout, quat_order)))
    for m in loaded:
        assert m.fps == pytest.approx(motion.fps, rel=1e-12)
        for key in ("root_pos", "root_quat", "dof_pos"):
            np.testing.assert_allclose(getattr(m, key), getattr(motion, key), rtol=0, atol=1e-12)
    fields = np.load(tmp_path / "fields.npz")
    kinematics = compute_kinematics(motion, build_humanoid())
    np.testing.assert_allclose(fields["body_pos"], kinematics.body_pos, atol=1e-12)
    assert str(fields["quat_order"]) == quat_order and "root_quat" not in fields.files  # never misread as wxyz


@pytest.mark.parametrize("up_axis", ["z", "y"])
def test_smpl_round_trip(exported, up_axis: str, tmp_path: Path) -> None:
    """``pose_aa``/``trans`` read back by crisp_gym.smpl put every body where the 30 fps motion has it."""
    clip, _ = exported
    data = np.load(write_motion_npz(clip.motion, tmp_path / "smpl.npz", "smpl", up_axis=up_axis))
    pose_aa, trans = data["pose_aa"], data["trans"]
    t = pose_aa.shape[0]
    assert pose_aa.shape == (t, 24, 3) and trans.shape == (t, 3) and float(data["fps"]) == 30.0
    assert tuple(data["joint_names"]) == SMPL_JOINT_NAMES
    back = load_smpl_params({"global_orient": pose_aa[:, 0], "body_pose": pose_aa[:, 1:].reshape(t, 69),
                             "transl": trans, "fps": data["fps"]}, up_axis=up_axis, to_floor=False)
    model = build_humanoid()
    expected = compute_kinematics(clip.motion.resample(30.0), model)
    got = compute_kinematics(back, model)
    assert np.abs(got.body_pos - expected.body_pos).max() < GEOMETRY_TOL
    angle = (Rotation.from_quat(got.body_quat.reshape(-1, 4), scalar_first=True).inv()
             * Rotation.from_quat(expected.body_quat.reshape(-1, 4), scalar_first=True)).magnitude()
    assert angle.max() < 1e-9
    if up_axis == "y":  # SMPL's own world: the pelvis height is trans' y
        np.testing.assert_allclose(trans[:, 1], clip.motion.resample(30.0).root_pos[:, 2], atol=1e-12)


def test_smpl_resamples_to_30_fps(sway_clip: Path, tmp_path: Path) -> None:
    motion = load_clip(sway_clip).motion.resample(60.0)
    data = np.load(write_motion_npz(motion, tmp_path / "smpl.npz", "smpl"))
    assert data["pose_aa"].shape[0] == motion.resample(30.0).num_frames


def test_motion_readers_reject_other_files(exported, tmp_path: Path) -> None:
    clip, _ = exported
    with pytest.raises(ValueError, match="neither"):
        read_motion_npz(clip.path / "motion.npz")
    (tmp_path / "bad.csv").write_text("frame,time\n0,0\n")
    with pytest.raises(ValueError, match="lacks the columns"):
        read_motion_csv(tmp_path / "bad.csv")
    with pytest.raises(ValueError, match="quat_order"):
        write_motion_csv(clip.motion, tmp_path / "m.csv", "xyz")


# ------------------------------------------------------------------------------------------------
# Policies


def _tiny_actor(kind: str, scene_aware: bool, num_future: int = 5, points: str = "pointnet"):
    from crisp_gym.policy.model_config import ModelConfig
    from crisp_gym.policy.networks import FixedStdGaussian, MLPActor, ObsNormalizer, TransformerActor

    torch.manual_seed(0)
    config = ModelConfig(actor=kind, latent_dim=32, ff_dim=64, num_layers=1, num_heads=2, pointnet_hidden=(16, 32),
                         mlp_actor_hidden=(32, 32), init_action_std=0.1,  # a visible output, not ~0
                         point_encoder=points)
    normalizer = ObsNormalizer(num_future)
    normalizer.update(torch.randn(256, 361) * 3 + 1, torch.randn(256, num_future, 432) * 2 - 1)
    cls = TransformerActor if kind == "transformer" else MLPActor
    return FixedStdGaussian(cls(num_future, 128 if scene_aware else 0, normalizer, config))


def _observations(batch: int, scene_aware: bool, num_points: int = 128, seed: int = 1) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    obs = (torch.randn(batch, 361, generator=g) * 3, torch.randn(batch, 5, 432, generator=g))
    return obs + ((torch.randn(batch, num_points, 3, generator=g),) if scene_aware else ())


@pytest.mark.parametrize("kind, scene_aware, points", [("mlp", False, "pointnet"), ("transformer", True, "pointnet"),
                                                       ("mlp", True, "flat")])
def test_policy_onnx_and_torchscript_match_torch(kind: str, scene_aware: bool, points: str, tmp_path: Path) -> None:
    import onnxruntime

    from crisp_gym.export.policy import export_inference_policy

    actor = _tiny_actor(kind, scene_aware, points=points)
    files = {p.name: p for p in export_inference_policy(actor, tmp_path)}
    session = onnxruntime.InferenceSession(str(files["policy.onnx"]))
    scripted = torch.jit.load(str(files["policy.pt"]))
    # a PointNet takes any number of points, a flat encoder the 128 it was built for
    for batch, num_points in ((1, 128), (6, 128 if points == "flat" else 40)):
        obs = _observations(batch, scene_aware, num_points)
        with torch.no_grad():
            expected = actor(*obs)[0].numpy()
            np.testing.assert_allclose(scripted(*obs).numpy(), expected, rtol=0, atol=1e-5)
        feed = {i.name: x.numpy() for i, x in zip(session.get_inputs(), obs)}
        (got,) = session.run(["action"], feed)
        assert got.shape == (batch, 69) and np.abs(expected).max() > 0.05
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)
    layout = json.loads(files["policy.json"].read_text())
    names = [i["name"] for i in layout["inputs"]]
    assert names == [i.name for i in session.get_inputs()] == ["proprio", "targets", "points"][: len(names)]
    assert layout["inputs"][0]["segments"][-1]["stop"] == 361
    assert layout["inputs"][1]["per_body_features"][-1]["stop"] * 24 == 432
    assert layout["output"]["joint_names"] == list(DOF_NAMES) and layout["output"]["mode"] == "residual"
    assert layout["control"] == {"control_hz": 30.0, "sim_hz": 120.0, "substeps": 4, "integrator": "implicitfast"}
    assert layout["pd"]["joints"]["L_Knee_y"]["kp"] == 800.0


def test_policy_layout_describes_the_env_observation() -> None:
    """The JSON's segments pick out known quantities of a real ``CrispTrack-v0`` observation."""
    from crisp_gym.envs.config import TrackConfig
    from crisp_gym.envs.track import CrispTrackEnv
    from crisp_gym.export.policy import policy_layout

    env = CrispTrackEnv("stairs_up")
    obs, _ = env.reset(options={"start_frame": 12})
    layout = policy_layout(TrackConfig(), scene_aware=False, num_future_frames=5)
    seg = {s["name"]: s for s in layout["inputs"][0]["segments"]}
    proprio = obs["proprio"]
    pelvis = env.data.xpos[env.model.body("Pelvis").id]
    assert proprio[seg["root_height"]["start"]] == pytest.approx(pelvis[2], abs=1e-6)
    body_pos = proprio[seg["body_pos"]["start"]:seg["body_pos"]["stop"]].reshape(24, 3)
    np.testing.assert_allclose(body_pos[0], 0.0, atol=1e-6)
    heading = Rotation.from_euler("z", Rotation.from_quat(env.data.xquat[1], scalar_first=True).as_euler("ZYX")[0])
    foot = env.data.xpos[env.model.body("L_Toe").id] - pelvis
    np.testing.assert_allclose(body_pos[BODY_NAMES.index("L_Toe")], heading.inv().apply(foot), atol=1e-5)
    feature = {s["name"]: s for s in layout["inputs"][1]["per_body_features"]}
    rel = obs["targets"].reshape(5, 24, 18)[0, 0, feature["ref_pos_rel_root"]["start"]:feature["ref_pos_rel_root"]["stop"]]
    reference = env.task.reference.body_pos[13, 0]
    np.testing.assert_allclose(rel, heading.inv().apply(reference - pelvis), atol=1e-5)


def test_cli_exports_a_checkpoint(tmp_path: Path) -> None:
    """The exported policy computes what the checkpoint's actor does, and its JSON says how its
    actions become PD targets (here with the velocity feedforward it was trained with)."""
    from crisp_gym.policy.model_config import ModelConfig
    from crisp_gym.train.checkpoints import load_policy, save_checkpoint
    from crisp_gym.train.config import cpu_profile
    from crisp_gym.train.ppo import build_agent

    cfg = cpu_profile(output=tmp_path / "run", model=ModelConfig(actor="mlp", mlp_actor_hidden=(32,), critic_hidden=(32,),
                                                                  init_action_std=0.1), velocity_feedforward=True)
    agent = build_agent(cfg.model, 5, 0)
    agent.normalizer.update(*_observations(64, False))
    cfg.output.mkdir()
    save_checkpoint(cfg.output / "checkpoint.pt", agent, torch.optim.Adam(agent.actor.parameters()), 1, 64, cfg,
                    torch.Generator())
    assert main([str(cfg.output), "--format", "torchscript", "-o", str(tmp_path / "out")]) == 0
    scripted = torch.jit.load(str(tmp_path / "out" / "policy" / "policy.pt"))
    obs = _observations(3, False, seed=4)
    with torch.no_grad():
        np.testing.assert_allclose(scripted(*obs).numpy(), load_policy(cfg.output)[0](*obs)[0].numpy(), atol=1e-6)
    layout = json.loads((tmp_path / "out" / "policy" / "policy.json").read_text())
    assert layout["files"] == ["policy.pt"] and layout["observation_normalization"]["clip"] == 5.0
    assert layout["track_config"]["velocity_feedforward"]
    assert "+ clip(kd / kp * reference hinge velocities of frame t+1, ±0.3)" in layout["output"]["mapping"]


# ------------------------------------------------------------------------------------------------
# Command line and bad input


def test_cli_clip_formats_and_errors(sway_clip: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main([str(sway_clip), "--format", "csv", "glb", "--quat-order", "xyzw", "-o", str(out)]) == 0
    assert read_motion_csv(out / "motion" / "motion.csv").num_frames == load_clip(sway_clip).motion.num_frames
    assert (out / "mesh" / "scene.glb").is_file() and not (out / "mjcf").exists()
    with pytest.raises(ValueError, match="separate calls"):
        export(ExportConfig(source=str(sway_clip), format=("mjcf", "onnx"), output=tmp_path / "new"))
    with pytest.raises(ValueError, match="unknown clip"):
        export(ExportConfig(source="no_such_clip", output=tmp_path / "new"))
    assert not (tmp_path / "new").exists()
    clip = load_clip(sway_clip)
    other = write_clip(tmp_path / "hfield", clip.boxes, clip.motion, {"scene_kind": "heightfield"})
    with pytest.raises(ValueError, match="box scenes"):
        export(ExportConfig(source=str(other), format=("urdf",), output=tmp_path / "x"))


def test_export_replaces_a_folder_whole_or_not_at_all(sway_clip: Path, tmp_path: Path, monkeypatch) -> None:
    """An existing export is refused without --overwrite; an export interrupted midway leaves the
    previous one exactly as it was (not a folder mixing two exports), with no temporary left."""
    out = tmp_path / "out"
    export(ExportConfig(source=str(sway_clip), format=("csv", "glb"), output=out))
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(FileExistsError, match="--overwrite"):
        export(ExportConfig(source=str(sway_clip), format=("csv",), output=out))

    import crisp_gym.export as export_module

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(export_module, "write_scene_mesh", interrupted)  # csv is written, then the mesh fails
    with pytest.raises(KeyboardInterrupt):
        export(ExportConfig(source=str(sway_clip), format=("csv", "glb"), output=out, overwrite=True,
                            quat_order="xyzw"))
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before and sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    monkeypatch.undo()
    files = export(ExportConfig(source=str(sway_clip), format=("csv",), output=out, overwrite=True, quat_order="xyzw"))
    assert files == [out / "motion" / "motion.csv"] and not (out / "mesh").exists()


def test_onnx_export_without_its_extra_names_it(tmp_path: Path, monkeypatch) -> None:
    """Without onnxscript torch's exporter fails deep inside; the export says which extra to install
    before writing anything."""
    import importlib.util

    from crisp_gym.export import policy as policy_export

    real = importlib.util.find_spec
    monkeypatch.setattr(policy_export.importlib.util, "find_spec",
                        lambda name, *a: None if name == "onnxscript" else real(name, *a))
    with pytest.raises(ModuleNotFoundError, match=r"onnxscript: pip install 'crisp-gym\[export\]'"):
        policy_export.export_inference_policy(_tiny_actor("mlp", False), tmp_path / "out")
    assert not (tmp_path / "out" / "policy.onnx").exists()


def test_humanoid_urdf_keeps_the_pelvis_and_takes_a_free_joint_in_mujoco(humanoid_urdf: Path) -> None:
    """MuJoCo fused the URDF's root link into the world and lost the 7.8 kg pelvis; with the
    file's MuJoCo extension it stays, and one free joint gives the floating base: the whole
    humanoid's mass and degrees of freedom, as the MJCF model has them."""
    from crisp_gym.export.urdf import UrdfConfig

    model = build_humanoid()
    spec = mujoco.MjSpec.from_file(str(humanoid_urdf))
    spec.body("Pelvis").add_freejoint()
    floating = spec.compile()
    pelvis = model.body("Pelvis").id
    np.testing.assert_allclose(floating.body_mass[floating.body("Pelvis").id], model.body_mass[pelvis])
    extra = floating.body_subtreemass[0] - model.body_subtreemass[0]  # the 46 intermediate links
    assert extra == pytest.approx(46 * UrdfConfig().link_mass)
    assert floating.nv == model.nv and floating.jnt_type[floating.body_jntadr[floating.body("Pelvis").id]] == 0
    assert len(yourdfpy.URDF.load(str(humanoid_urdf)).robot.links) == floating.nbody - 1  # other readers skip it


def test_dm_control_physics_builds_and_steps_under_this_mujoco(exported) -> None:
    """dm_control 1.0.50 binds fields MuJoCo 4 removed (``flex_vertedge``): ``mjcf.Physics`` failed
    on every model. Without those bindings the composed export builds, steps, and follows
    MuJoCo's own compile of the same XML exactly."""
    from dm_control import mjcf

    from crisp_gym.export.dm_control_compat import drop_missing_bindings

    drop_missing_bindings()
    assert drop_missing_bindings() == []  # idempotent
    clip, out = exported
    arena = mjcf.from_path(str(out / "dm_control" / "arena.xml"))
    arena.attach(mjcf.from_path(str(out / "dm_control" / "walker.xml"))).add("freejoint")
    physics = mjcf.Physics.from_mjcf_model(arena)
    reference = mujoco.MjModel.from_xml_string(arena.to_xml_string(), arena.get_assets())
    data = mujoco.MjData(reference)
    start = clip.motion.num_frames // 3
    for target in (physics.data, data):
        target.qpos[:] = clip.motion.qpos()[start]
        target.qvel[:] = clip.motion.qvel()[start]
    physics.named.data.ctrl["crisp_humanoid/L_Knee_y"] = 0.3
    data.ctrl[reference.actuator("crisp_humanoid/L_Knee_y").id] = 0.3
    physics.forward()  # dm_control steps as mj_step2 then mj_step1: both start from a forward pass
    mujoco.mj_forward(reference, data)
    for _ in range(20):
        physics.step()
        mujoco.mj_step(reference, data)
    assert np.abs(physics.data.qpos - data.qpos).max() <= 1e-9
    assert physics.named.data.xpos["crisp_humanoid/Pelvis"][2] > 0.5  # still standing after 20 steps
