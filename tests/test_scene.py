import json

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crisp_gym.clip import load_clip_dir, write_clip
from crisp_gym.registry import list_clips, load_clip, register_clip, resolve_clip
from crisp_gym.scene import (
    Box,
    build_scene_spec,
    floor_box,
    load_primitives,
    load_scene_xml,
    sample_surface_points,
    save_primitives,
    write_scene_xml,
)
from tests.conftest import sway_motion


def _boxes():
    rot = Rotation.from_euler("xyz", [0.1, -0.2, 0.7]).as_matrix()
    return [floor_box(), Box(center=[1, 2, 0.3], rotation=rot, half_size=[0.4, 0.2, 0.3], source="contact", name="seat")]


def test_primitives_json_and_scene_xml_round_trip(tmp_path):
    boxes = _boxes()
    save_primitives(boxes, tmp_path / "primitives.json")
    items = json.loads((tmp_path / "primitives.json").read_text())
    assert set(items[1]) == {"center", "rotation", "half_size", "source", "name"} and len(items[1]["rotation"]) == 9
    for a, b in zip(boxes, load_primitives(tmp_path / "primitives.json")):
        np.testing.assert_allclose(a.center, b.center)
        np.testing.assert_allclose(a.rotation, b.rotation)
        assert a.source == b.source
    write_scene_xml(boxes, tmp_path / "scene.xml")
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "scene.xml"))  # loads on its own
    assert model.ngeom == 2 and model.nbody == 1
    for a, b in zip(boxes, load_scene_xml(tmp_path / "scene.xml")):
        np.testing.assert_allclose(a.corners(), b.corners(), atol=1e-6)  # MJCF stores ~7 digits


def test_bad_boxes_are_rejected():
    with pytest.raises(ValueError, match="positive"):
        Box(center=[0, 0, 0], half_size=[1, 0, 1])
    with pytest.raises(ValueError, match="rotation"):
        Box(center=[0, 0, 0], rotation=np.diag([1, 1, -1.0]))
    with pytest.raises(ValueError, match="source"):
        Box(center=[0, 0, 0], source="guess")
    with pytest.raises(ValueError, match="at least one"):
        build_scene_spec([])


def test_surface_points_lie_on_faces_with_outward_normals():
    box = _boxes()[1]
    points, normals = sample_surface_points([box], spacing=0.05, rng=np.random.default_rng(0))
    local = (points - box.center) @ box.rotation
    # every point is on the surface: one coordinate at ±half size, the others inside
    on_face = np.isclose(np.abs(local), box.half_size, atol=1e-9)
    assert np.all(on_face.any(axis=1)) and np.all(np.abs(local) <= box.half_size + 1e-9)
    assert np.all(np.einsum("ij,ij->i", normals, points - box.center) > 0)
    area = 8 * (box.half_size[0] * box.half_size[1] + box.half_size[1] * box.half_size[2]
                + box.half_size[0] * box.half_size[2])
    assert len(points) == pytest.approx(area / 0.05 ** 2, rel=0.15)


def test_clip_write_is_atomic_and_registry_resolves(tmp_path):
    motion = sway_motion(frames=10)
    path = write_clip(tmp_path / "c", _boxes(), motion, {"source": "test"})
    (tmp_path / "plain").mkdir()
    assert path.stat().st_mode & 0o777 == (tmp_path / "plain").stat().st_mode & 0o777  # as a mkdir, not 0700
    clip = load_clip_dir(path)
    assert clip.meta["num_primitives"] == 2 and clip.meta["num_contact_primitives"] == 1
    with pytest.raises(FileExistsError):
        write_clip(path, _boxes(), motion)

    class Interrupt(Exception):
        pass

    bad = sway_motion(frames=10)
    object.__setattr__(bad, "save", lambda p: (_ for _ in ()).throw(Interrupt()))
    with pytest.raises(Interrupt):
        write_clip(tmp_path / "half", _boxes(), bad)
    assert not (tmp_path / "half").exists() and not list(tmp_path.glob(".half*"))

    register_clip("mine", path, tags=["test"])
    assert resolve_clip("mine") == path.resolve() and "mine" in list_clips()
    assert load_clip("mine").motion.num_frames == 10
    with pytest.raises(ValueError, match="unknown clip"):
        resolve_clip("no_such_clip")
    (path / "meta.json").unlink()
    with pytest.raises(FileNotFoundError, match="meta.json"):
        load_clip_dir(path)


def test_transformed_box_moves_its_corners_rigidly():
    box = Box(center=[1.0, 2.0, 0.5], rotation=Rotation.from_euler("z", 0.3).as_matrix(), half_size=[0.2, 0.4, 0.1])
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", [0.1, -0.2, 1.0]).as_matrix()
    m[:3, 3] = [0.5, -1.0, 2.0]
    moved = box.transformed(m)
    np.testing.assert_allclose(moved.corners(), box.corners() @ m[:3, :3].T + m[:3, 3], atol=1e-12)
    assert moved.source == box.source and moved.name == box.name
