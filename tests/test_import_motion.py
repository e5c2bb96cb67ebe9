"""``crisp import-motion``: every layout read at its own frame rate, up axis detected, grounded per
frame; exports read back by the importer (round trips); folders; names checked before any work.

Files are made by the tests from bundled clips (the exporters write them) or by hand; the real
SMPL motions estimated from videos are used when ``../shared/data`` is present.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from crisp_gym import cli
from crisp_gym.export.motion_formats import amass_layout, beyondmimic_layout, smpl_layout, write_motion_npz
from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, build_humanoid
from crisp_gym.import_motion import ImportMotionArgs, import_motion, read_motion
from crisp_gym.metrics import sole_points
from crisp_gym.motion import (
    Motion,
    check_plausible,
    compute_kinematics,
    ground_stance,
    planted_feet,
    side_sole_heights,
)
from crisp_gym.registry import check_clip_name, list_clips, load_clip, plain_clip_name, user_registry_path
from crisp_gym.smpl import SMPL_TO_OURS, detect_up_axis

from .conftest import SHARED_DATA, fold_leg

ASAP = SHARED_DATA / "asap_video_smpl"
ROUND_TRIP_TOL = 1e-3  # m, the bound on joint positions after export -> import


@pytest.fixture(scope="module")
def model():
    return build_humanoid()


@pytest.fixture(scope="module")
def walk() -> Motion:
    return load_clip("flat_walk").motion


def _joint_error(a: Motion, b: Motion, model) -> float:
    assert a.num_frames == b.num_frames
    return float(np.abs(compute_kinematics(a, model).body_pos - compute_kinematics(b, model).body_pos).max())


@pytest.mark.parametrize("clip", ["flat_walk", "chair_sit"])
@pytest.mark.parametrize("layout", ["beyondmimic", "amass", "smpl", "fields", "qpos"])
def test_export_then_import_reproduces_the_joints(layout, clip, model, tmp_path):
    """A grounded clip goes out in a layout and back through the importer with every joint within
    1 mm: exactly with one grounding offset, and within 1 mm (2 mm for the SMPL family, whose
    planted feet the importer lays flat as a capture's, re-posing the toes) with the default
    per-frame grounding."""
    motion = load_clip(clip).motion
    path = write_motion_npz(motion, tmp_path / f"{layout}.npz", layout)
    read = read_motion(path, grounding="constant", model=model)
    assert read.source_fps == motion.fps and read.motion.num_frames == motion.num_frames
    assert _joint_error(read.motion, motion, model) < 1e-6
    default = read_motion(path, model=model)
    assert _joint_error(default.motion, motion, model) < (2e-3 if layout in ("amass", "smpl") else ROUND_TRIP_TOL)
    if layout in ("amass", "smpl"):
        assert read.up_axis == "z"


def test_stance_grounding_flattens_a_climb_and_says_so(model, tmp_path):
    """import-motion makes flat-ground clips: per-frame grounding puts a stair climb's planted feet
    on the floor (one offset keeps it), and the report tells the user."""
    motion = load_clip("stairs_up").motion
    path = write_motion_npz(motion, tmp_path / "climb.npz", "beyondmimic")
    read = read_motion(path, model=model)
    assert read.ground_shift[0] < -0.1
    assert "--grounding constant" in read.describe()
    assert "--grounding constant" not in read_motion(path, grounding="constant", model=model).describe()


def test_beyondmimic_layout_holds_world_body_states(walk, model):
    data = beyondmimic_layout(walk)
    kin = compute_kinematics(walk, model)
    assert tuple(data["body_names"]) == BODY_NAMES and float(data["fps"][0]) == walk.fps
    np.testing.assert_allclose(data["body_pos_w"], kin.body_pos)
    # Velocities agree with finite differences of the poses they come with.
    mid = slice(5, -5)
    np.testing.assert_allclose(data["body_lin_vel_w"][mid], np.gradient(kin.body_pos, 1 / walk.fps, axis=0)[mid])
    np.testing.assert_allclose(data["joint_vel"][mid], np.gradient(walk.dof_pos, 1 / walk.fps, axis=0)[mid],
                               atol=1e-9)
    # The root body is the first one: its pose is the motion's root.
    np.testing.assert_allclose(data["body_pos_w"][:, 0], walk.root_pos, atol=1e-12)


def _amass_file(path: Path, motion: Motion, *, fps: float, up: str = "z", pickled_gender: bool = False) -> Path:
    """An AMASS-layout file of ``motion`` as written by other tools: float32, a y-up variant,
    ``gender`` optionally as a pickled object array."""
    data = amass_layout(motion)
    poses, trans = data["poses"], data["trans"]
    if up == "y":  # the same motion in SMPL's own y-up world
        from scipy.spatial.transform import Rotation

        to_y = SMPL_TO_OURS.T
        root = Rotation.from_matrix(to_y) * Rotation.from_rotvec(poses[:, :3])
        poses = np.concatenate([root.as_rotvec(), poses[:, 3:]], axis=1)
        trans = trans @ to_y.T
    gender = np.array("neutral", dtype=object) if pickled_gender else np.array("neutral")
    np.savez(path, poses=poses.astype(np.float32), trans=trans.astype(np.float32), betas=np.zeros(16),
             gender=gender, mocap_framerate=np.array(fps))
    return path


def test_amass_frame_rate_comes_from_the_file(walk, model, tmp_path):
    """A 120 fps file plays at 120 fps: its 30 fps clip lasts a quarter as long (the old CLI
    default played it 4x slow)."""
    path = _amass_file(tmp_path / "fast.npz", walk, fps=120.0)
    read = read_motion(path, fps=30.0, model=model)
    assert read.source_fps == 120.0
    assert read.motion.duration == pytest.approx((walk.num_frames - 1) / 120.0, abs=1 / 30)
    # An override wins over the file.
    assert read_motion(path, source_fps=30.0, model=model).motion.num_frames == walk.num_frames


@pytest.mark.parametrize("up", ["z", "y"])
def test_up_axis_is_detected(up, walk, model, tmp_path):
    path = _amass_file(tmp_path / f"{up}.npz", walk, fps=30.0, up=up)
    read = read_motion(path, model=model)
    assert read.up_axis == up
    assert _joint_error(read.motion, walk, model) < 2e-3  # float32 storage
    # Forcing the wrong axis lays the body down: the pelvis near the floor, as the issue saw.
    wrong = read_motion(path, up_axis="y" if up == "z" else "z", model=model).motion
    assert np.median(wrong.root_pos[:, 2]) < 0.5 < np.median(read.motion.root_pos[:, 2])


def test_pickled_entries_are_skipped_not_loaded(walk, model, tmp_path):
    path = _amass_file(tmp_path / "pickled.npz", walk, fps=30.0, pickled_gender=True)
    with pytest.raises(ValueError):  # the file really holds a pickle
        np.load(path, allow_pickle=False)["gender"]
    assert read_motion(path, model=model).motion.num_frames == walk.num_frames


def test_smpl_parameters_without_a_frame_rate_need_one(walk, model, tmp_path):
    smpl = smpl_layout(walk, "z")
    t = len(smpl["pose_aa"])
    path = tmp_path / "gvhmr.npz"
    np.savez(path, global_orient=smpl["pose_aa"][:, 0], body_pose=smpl["pose_aa"][:, 1:].reshape(t, 69),
             transl=smpl["trans"])
    with pytest.raises(ValueError, match="--source-fps"):
        read_motion(path, model=model)
    read = read_motion(path, source_fps=30.0, model=model)
    assert read.up_axis == "z" and _joint_error(read.motion, walk, model) < 2e-3


def test_detect_up_axis_scores_uprightness():
    upright = {"global_orient": np.zeros((4, 3))}  # SMPL's rest body in its own y-up world
    axis, score = detect_up_axis(upright)
    assert axis == "y" and score["y"] == pytest.approx(1.0) and abs(score["z"]) < 1e-9


def test_a_jump_in_place_keeps_its_flight(model):
    """A foot still at the top of a jump is not planted: per-frame grounding must not pull the
    flight down to the floor (horizontal stillness alone called the whole flight a stance)."""
    fps, t = 30.0, np.arange(60) / 30.0
    flight = (t > 1.0) & (t < 1.5)
    height = 0.93 + np.where(flight, 0.5 * 9.81 * (t - 1.0) * (1.5 - t), 0.0)  # 31 cm apex
    motion = Motion(fps=fps, root_pos=np.c_[np.zeros(60), np.zeros(60), height],
                    root_quat=np.tile([1.0, 0, 0, 0], (60, 1)), dof_pos=np.zeros((60, 69)))
    planted = planted_feet(motion, model).any(axis=1)
    near_flight = np.convolve(flight, np.ones(3), mode="same") > 0  # central differences see takeoff and landing
    assert planted[~near_flight][1:-1].all() and not planted[flight].any()
    grounded = ground_stance(motion, model)
    rise = grounded.root_pos[:, 2] - grounded.root_pos[0, 2]
    np.testing.assert_allclose(rise, height - height[0], atol=0.01)


def test_folder_import_names_clips_and_reports_failures(walk, tmp_path, capsys):
    folder = tmp_path / "takes"
    folder.mkdir()
    write_motion_npz(walk, folder / "walk one.npz", "beyondmimic")
    _amass_file(folder / "walk_two.npz", walk, fps=30.0)
    (folder / "broken.npz").write_bytes(b"not an archive")
    (folder / "notes.txt").write_text("ignored")
    code = cli.main(["import-motion", str(folder), "--name", "take", "-o", str(tmp_path / "clips")])
    assert code == 2  # one file failed
    err = capsys.readouterr().err
    assert "broken.npz" in err and "not a readable npz" in err
    clips = list_clips()
    assert {"take_walk_one", "take_walk_two"} <= set(clips) and "take_broken" not in clips
    assert load_clip("take_walk_one").meta["source_format"] == "BeyondMimic"


def test_an_import_says_where_its_body_cannot_balance(walk, tmp_path, capsys):
    """The bundled walk is balanced by construction; lifted 5 cm off the floor from frame 40 on,
    it hovers, and the report names those frames (in ``meta.json`` and on the terminal)."""
    lifted = replace(walk, root_pos=walk.root_pos + np.where(np.arange(walk.num_frames)[:, None] >= 40, [0, 0, 0.05], 0))
    for name, motion in (("walk_as_is", walk), ("walk_lifted", lifted)):
        path = write_motion_npz(motion, tmp_path / f"{name}.npz", "beyondmimic")
        assert cli.main(["import-motion", str(path), "--name", name, "-o", str(tmp_path / name),
                         "--grounding", "constant"]) == 0
    out = capsys.readouterr().out
    as_is, lifted_meta = (load_clip(n).meta["followability"] for n in ("walk_as_is", "walk_lifted"))
    assert as_is["unsupported"] == 0.0 and "a body can follow it" in out
    assert lifted_meta["unsupported"] > 0.5 and lifted_meta["spans"][-1][1] == walk.num_frames
    assert 38 <= lifted_meta["spans"][0][0] <= 42 and "no foot down under load" in out


@pytest.mark.parametrize("name", ["../../escape", "a b", "", ".hidden", "x/y"])
def test_bad_names_are_refused_before_any_work(name, walk, tmp_path):
    path = write_motion_npz(walk, tmp_path / "m.npz", "beyondmimic")
    with pytest.raises(ValueError, match="plain names"):
        import_motion(ImportMotionArgs(file=path, name=name, output=tmp_path / "out"))
    assert not (tmp_path / "out").exists() and not user_registry_path().exists()


@pytest.mark.parametrize("text, name", [("my video", "my_video"), (".hidden", "_.hidden"), ("a/b\\c", "a_b_c"),
                                        ("take-2.v1", "take-2.v1"), ("é+x", "é+x")])
def test_file_stems_become_plain_names(text, name):
    assert plain_clip_name(text) == name
    assert check_clip_name(name) == name


@pytest.mark.skipif(not ASAP.is_dir(), reason="../shared/data/asap_video_smpl is not present")
@pytest.mark.parametrize("stem", ["video_walk_level3_filter_amass", "video_single_foot_jump_level2_filter_amass",
                                  "video_squat_level2_filter_amass"])
def test_real_video_smpl_imports_grounded(stem, model):
    """Real AMASS files as published: z up detected, their own 30 fps, and the lowest planted foot
    within 1 cm of the floor (median) where one constant offset left it 1-6 cm off."""
    read = read_motion(ASAP / f"{stem}.npz", model=model)
    assert read.source_format == "AMASS" and read.up_axis == "z" and read.source_fps == 30.0
    planted = planted_feet(read.motion, model)
    soles = sole_points(model, read.motion.qpos())
    lowest = np.where(planted, np.minimum(soles[:, 0::2, 2], soles[:, 1::2, 2]), np.inf).min(axis=1)
    assert np.isfinite(lowest).mean() > 0.3
    assert abs(np.median(lowest[np.isfinite(lowest)])) < 0.01


def test_a_registry_with_a_path_for_a_name_is_refused(tmp_path):
    registry = user_registry_path()
    registry.parent.mkdir(parents=True, exist_ok=True)
    registry.write_text(f"clips:\n  ../../x:\n    path: {tmp_path}\n")
    with pytest.raises(ValueError, match=r"registry.yaml: '../../x' is not a plain clip name"):
        list_clips()


@pytest.mark.parametrize("rate, message", [(1e-4, "frames at 30 fps"), (1e7, "not a capture's")])
def test_impossible_frame_rates_fail_before_resampling(rate, message, walk, model, tmp_path):
    """A header that says 1e-4 fps would resample 185 frames into 55 M (the issue's MemoryError);
    one that says 1e7 fps is no capture. Both are refused before resampling (which would fail
    with a MemoryError, not this message), naming the rate."""
    path = _amass_file(tmp_path / "bad_rate.npz", walk, fps=rate)
    with pytest.raises(ValueError, match=message):
        read_motion(path, model=model)


@pytest.mark.parametrize("corrupt, message", [
    (lambda m: m.root_pos.__setitem__((40, 0), 5.6e298), "frame 40: the root is 5.6e\\+298 m"),
    (lambda m: m.root_pos.__setitem__((slice(40, None), 2), m.root_pos[40:, 2] + 3.0), "frame 39: the root moves at"),
    (lambda m: m.dof_pos.__setitem__((70, DOF_NAMES.index("R_Elbow_y")), 40.0), "frame 69: hinge R_Elbow_y speed"),
])  # fmt: skip
def test_motions_no_body_can_do_are_refused_naming_frame_and_joint(corrupt, message, walk, model, tmp_path):
    motion = replace(walk, root_pos=walk.root_pos.copy(), dof_pos=walk.dof_pos.copy(), contacts=None)
    corrupt(motion)
    path = motion.save(tmp_path / "motion.npz")
    with pytest.raises(ValueError, match=message):
        read_motion(path, model=model)
    check_plausible(walk)  # the bundled walk passes


def test_a_motion_shorter_than_one_output_frame_says_so(walk, model, tmp_path):
    """Two frames at 120 fps last 8 ms: resampled to 30 fps they are one frame. The message says
    that, not only that a motion needs two frames (which the file has)."""
    path = replace(walk.slice(0, 2), fps=120.0, contacts=None).save(tmp_path / "short.npz")
    with pytest.raises(ValueError, match=r"lasts 0.00833 s \(2 frames at 120 fps\), less than one frame at 30 fps"):
        read_motion(path, model=model)


def test_a_clip_no_body_can_do_is_refused_by_every_command_that_loads_it(walk, tmp_path, capsys):
    """The issue's 1e300 BVH became a clip that export wrote to every format and training crashed
    on. A clip written by other means (here directly) is checked where clips are loaded."""
    from crisp_gym.clip import load_clip_dir, write_clip
    from crisp_gym.scene import floor_box

    motion = replace(walk, root_pos=walk.root_pos.copy(), contacts=None)
    motion.root_pos[40, 0] = 5.6e298
    clip = write_clip(tmp_path / "bad", [floor_box()], motion, {"source": "test"})
    with pytest.raises(ValueError, match=r"bad/motion.npz: frame 40: the root is 5.6e\+298 m"):
        load_clip_dir(clip)
    assert cli.main(["export", str(clip), "-o", str(tmp_path / "out")]) == 2
    assert "frame 40: the root is 5.6e+298 m" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def _protomotions_file(path: Path, motion: Motion, model, **changes) -> Path:
    """A ProtoMotions ``.motion`` as its tools save one: a torch dict, world body states with
    x y z w quaternions (made here from MuJoCo's forward kinematics, not by the reader's module)."""
    import torch

    kin = compute_kinematics(motion, model)
    content = {"dof_pos": torch.tensor(motion.in_humanoid_order().dof_pos, dtype=torch.float32),
               "rigid_body_pos": torch.tensor(kin.body_pos, dtype=torch.float32),
               "rigid_body_rot": torch.tensor(np.roll(kin.body_quat, -1, axis=-1), dtype=torch.float32),
               "dof_vel": torch.zeros(motion.num_frames, len(DOF_NAMES)), "fps": motion.fps} | changes
    torch.save(content, path)
    return path


@pytest.mark.parametrize("clip", ["flat_walk", "chair_sit"])
def test_protomotions_files_import_with_every_joint_in_place(clip, model, tmp_path):
    motion = load_clip(clip).motion
    path = _protomotions_file(tmp_path / f"{clip}.motion", motion, model)
    read = read_motion(path, grounding="constant", model=model)
    assert read.source_format == "ProtoMotions" and read.source_fps == motion.fps
    assert _joint_error(read.motion, motion, model) < 1e-4  # float32 storage
    assert _joint_error(read_motion(path, model=model).motion, motion, model) < 2e-3  # feet laid flat


def test_protomotions_files_are_read_without_running_code(walk, model, tmp_path):
    import torch

    class Payload:
        def __reduce__(self):
            return (Path.touch, (tmp_path / "ran",))

    torch.save({"dof_pos": Payload(), "fps": 30.0}, tmp_path / "evil.motion")
    with pytest.raises(ValueError, match="not a torch file of tensors and plain values"):
        read_motion(tmp_path / "evil.motion", model=model)
    assert not (tmp_path / "ran").exists()
    bad = _protomotions_file(tmp_path / "bad.motion", walk, model, rigid_body_rot=torch.zeros(3, 24, 4))
    with pytest.raises(ValueError, match=r"rigid_body_rot must have shape \(T, 24, 4\)"):
        read_motion(bad, model=model)
    swapped = _protomotions_file(tmp_path / "wxyz.motion", walk, model)  # quaternions in the other order
    content = torch.load(swapped, weights_only=True)
    content["rigid_body_rot"] = content["rigid_body_rot"].roll(1, dims=-1)
    torch.save(content, swapped)
    with pytest.raises(ValueError, match=r"conventions \(hinge order, quaternion order x y z w"):
        read_motion(swapped, model=model)


def test_import_plants_a_hovering_foot_when_told_to(model, tmp_path):
    """Standing on the right foot with the left one held still 3-4 cm up (the leg folded at hip,
    knee and ankle): imported with ``--plant-feet``, the left foot stands on the floor; by default
    it stays where it was, and ``meta.json`` says which was done."""
    lift = 0.3
    dof = np.zeros((45, len(DOF_NAMES)))
    fold_leg(dof, "L", lift)
    standing = Motion(fps=30.0, root_pos=np.tile([0.0, 0.0, 0.95], (45, 1)), root_quat=np.tile([1.0, 0, 0, 0], (45, 1)),
                      dof_pos=dof)
    path = write_motion_npz(standing, tmp_path / "stand.npz", "beyondmimic")
    for name, flags in (("planted", ["--plant-feet"]), ("as_read", [])):
        assert cli.main(["import-motion", str(path), "--name", name, "-o", str(tmp_path / name), *flags]) == 0
    planted, as_read = (load_clip(n) for n in ("planted", "as_read"))
    assert planted.meta["plant_feet"] is True and as_read.meta["plant_feet"] is False
    left = side_sole_heights(planted.motion, model)[:, 0]
    assert np.all((left > -1e-3) & (left < 3e-3))
    assert np.all(side_sole_heights(as_read.motion, model)[:, 0] > 0.03)


def test_import_stands_the_foot_that_carries_the_body_on_the_floor_when_told_to(model, tmp_path):
    """Crouched on both legs, the right one folded further (its foot ~4 cm above the left), while
    the body accelerates towards its left at 1.1 m/s²: the centre of pressure then lies under the
    right foot (height x acceleration / g, about 10 cm to the right of the centre of mass). The
    import grounds the lower, left foot; with ``--plant-support`` the right foot is brought down onto
    the floor, by default it stays up, and ``meta.json`` says which was done."""
    frames = 45
    dof = np.zeros((frames, len(DOF_NAMES)))
    for side, lift in (("L", 0.3), ("R", 0.45)):
        fold_leg(dof, side, lift)
    t = np.arange(frames) / 30.0
    root = np.stack([np.zeros(frames), 0.5 * 1.1 * t**2, np.full(frames, 0.9)], axis=1)
    leaning = Motion(fps=30.0, root_pos=root, root_quat=np.tile([1.0, 0, 0, 0], (frames, 1)), dof_pos=dof)
    path = write_motion_npz(leaning, tmp_path / "lean.npz", "beyondmimic")
    for name, flags in (("supported", ["--plant-support"]), ("as_read", [])):
        assert cli.main(["import-motion", str(path), "--name", name, "-o", str(tmp_path / name), *flags]) == 0
    supported, as_read = (load_clip(n) for n in ("supported", "as_read"))
    assert supported.meta["plant_support"] is True and as_read.meta["plant_support"] is False
    inner = slice(3, -3)  # away from the ends, whose accelerations are not measured
    before, after = side_sole_heights(as_read.motion, model)[inner], side_sole_heights(supported.motion, model)[inner]
    assert np.all(before[:, 0] < 3e-3) and np.all(before[:, 1] > 0.03)
    assert np.all((after[:, 1] > -1e-3) & (after[:, 1] < 3e-3))
    np.testing.assert_allclose(after[:, 0], before[:, 0], atol=1e-9)


def test_a_segment_holds_exactly_those_frames_of_the_whole_import(walk, tmp_path, capsys):
    """``--frames`` cuts after grounding and planting over the whole motion, so a segment equals
    the same frames of the whole import bit for bit (open and negative bounds as Python slices)."""
    path = write_motion_npz(walk, tmp_path / "walk.npz", "beyondmimic")
    assert cli.main(["import-motion", str(path), "--name", "whole", "-o", str(tmp_path / "whole"),
                     "--plant-support"]) == 0
    whole = load_clip("whole").motion
    total = whole.num_frames
    for name, spec, (start, stop) in (("middle", "60:110", (60, 110)), ("tail", "-40:", (total - 40, total)),
                                      ("head", ":30", (0, 30))):
        assert cli.main(["import-motion", str(path), "--name", name, "-o", str(tmp_path / name), "--plant-support",
                         "--frames", spec]) == 0
        segment = load_clip(name)
        assert segment.meta["frames"] == [start, stop] and segment.motion.num_frames == stop - start
        for field in ("root_pos", "root_quat", "dof_pos"):
            np.testing.assert_array_equal(getattr(segment.motion, field), getattr(whole, field)[start:stop])
    assert f"{total} frames at 30 fps" in capsys.readouterr().out.split("kept frames 60:110")[0]
    assert "frames" not in load_clip("whole").meta


@pytest.mark.parametrize("spec, message", [("60-110", "START:STOP"), ("a:b", "START:STOP"), ("1:2:3", "START:STOP"),
                                           ("0:100000", "outside the motion's"), ("50:51", "keeps 1 of"),
                                           ("110:60", "keeps 0 of")])
def test_bad_frame_ranges_are_refused_naming_the_range(spec, message, walk, tmp_path):
    path = write_motion_npz(walk, tmp_path / "walk.npz", "beyondmimic")
    with pytest.raises(ValueError, match=message):
        import_motion(ImportMotionArgs(file=path, name="cut", output=tmp_path / "cut", frames=spec))
    assert not (tmp_path / "cut").exists()
