"""TSDF baselines: the fused mesh against the true boxes, its colliders against the mesh and the
truth, and the clips in MuJoCo and in ``CrispTrack-v0``."""

import json

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from scipy.spatial import ConvexHull, cKDTree

import crisp_gym  # noqa: F401  (registers CrispTrack-v0)
from crisp_gym.clip import load_clip_dir
from crisp_gym.envs.track import CrispTrackEnv
from crisp_gym.geometry import intrinsic_from_fov, look_at
from crisp_gym.metrics import box_signed_distance, support_tops
from crisp_gym.mjcf_scene import scene_surface
from crisp_gym.motion import Motion
from crisp_gym.reconstruct.baselines import (
    ColliderConfig,
    TsdfConfig,
    convex_pieces_clip,
    dense_mesh_clip,
    heightfield_clip,
    mesh_to_convex_pieces,
    mesh_to_heightfield,
    tsdf_mesh,
    write_baseline_clips,
)  # fmt: skip
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.raycast import DepthRenderer, box_mesh
from crisp_gym.registry import load_clip
from crisp_gym.scene import SCENE_CONAFFINITY, SCENE_CONTYPE, Box, write_scene_xml

VOXEL = 0.03
RESOLUTION = 0.05
CENTER = np.array([2.2, 0.0, 0.2])  # the middle of stairs_up's flight
FEET = ("L_Ankle", "L_Toe", "R_Ankle", "R_Toe")


def orbit_frames(boxes: list[Box], views: int = 12, width: int = 160, extra: Box | None = None) -> Frames:
    """Depth of ``boxes`` from cameras circling the flight (``extra``: a masked 'person')."""
    renderer = DepthRenderer([box_mesh(b) for b in boxes])
    k = intrinsic_from_fov(width, width * 3 // 4, 70.0)
    poses = [look_at(CENTER + [3.5 * np.cos(a), 3.5 * np.sin(a), 2.2], CENTER)
             for a in np.linspace(0, 2 * np.pi, views, endpoint=False)]
    depth, masks = [], []
    for pose in poses:
        d, ids = renderer.render(k, pose, width, width * 3 // 4, dynamic=[box_mesh(extra)] if extra else [])
        depth.append(d)
        masks.append(ids == len(boxes))
    return Frames(depth=np.stack(depth), intrinsic=k, cam_c2w=np.stack(poses), person_mask=np.stack(masks))


@pytest.fixture(scope="module")
def clip():
    return load_clip("stairs_up")


@pytest.fixture(scope="module")
def mesh(clip):
    return tsdf_mesh(orbit_frames(clip.boxes), TsdfConfig(voxel_size=VOXEL, depth_max=4.5, weight_threshold=2.0),
                     progress=False)


@pytest.fixture(scope="module")
def field(mesh):
    return mesh_to_heightfield(mesh, RESOLUTION)


@pytest.fixture(scope="module")
def pieces(mesh):
    return mesh_to_convex_pieces(mesh, progress=False)


@pytest.fixture(scope="module")
def clips(tmp_path_factory, clip, mesh, field, pieces):
    out = tmp_path_factory.mktemp("baselines")
    return {
        "heightfield": heightfield_clip(out / "hf", field, clip.motion),
        "convex_pieces": convex_pieces_clip(out / "pieces", pieces, clip.motion),
        "dense_mesh": dense_mesh_clip(out / "dense", mesh, clip.motion),
    }


def inside(hull, points: np.ndarray, tol: float = 0.0) -> np.ndarray:
    """Which ``points`` lie in the convex ``hull`` (within ``tol``), by qhull's facet planes."""
    planes = ConvexHull(hull.vertices).equations  # outward normal n, offset d: n·x + d <= 0 inside
    near = np.flatnonzero(np.all((points >= hull.bounds[0] - tol) & (points <= hull.bounds[1] + tol), axis=1))
    result = np.zeros(len(points), bool)
    result[near] = np.all(points[near] @ planes[:, :3].T + planes[:, 3] <= tol, axis=1)
    return result


def true_top(xy: np.ndarray, boxes: list[Box]) -> np.ndarray:
    """Highest true surface above each xy."""
    return np.nanmax(support_tops(xy, boxes), axis=1)


def test_tsdf_mesh_lies_on_and_covers_the_true_surfaces(mesh, clip):
    dist = np.abs(box_signed_distance(mesh.vertices, clip.boxes))
    assert np.percentile(dist, 99) < 0.5 * VOXEL and np.percentile(dist, 99.9) < VOXEL
    assert dist.max() < 2 * VOXEL  # marching cubes' artefacts at the blocks' corners
    # Unbiased: the floor is at z = 0 (a half-pixel slip in the projection puts it ~1 cm low).
    floor = (mesh.vertices[:, 2] < 0.05) & (np.linalg.norm(mesh.vertices[:, :2] - CENTER[:2], axis=1) > 1.5)
    assert abs(np.median(mesh.vertices[floor, 2])) < 0.1 * VOXEL
    # Complete: every tread and the landing, seen from all around, is in the mesh.
    tops = [b for b in clip.boxes if b.name != "floor"]
    grid = np.stack(np.meshgrid(np.linspace(-0.95, 0.95, 12), np.linspace(-0.95, 0.95, 12)), -1).reshape(-1, 2)
    samples = np.concatenate([np.c_[b.center[:2] + grid * b.half_size[:2], np.full(len(grid), b.top_height())]
                              for b in tops])
    assert np.all(cKDTree(mesh.vertices).query(samples)[0] < VOXEL)


def test_tsdf_leaves_out_the_person_and_rejects_unusable_depth(clip):
    person = Box(center=[0.8, 0.0, 0.85], half_size=[0.15, 0.2, 0.85])
    frames = orbit_frames(clip.boxes, views=6, width=120, extra=person)
    cfg = TsdfConfig(voxel_size=0.05, depth_max=4.5, weight_threshold=1.0)

    def on_person(mesh):  # vertices on the person's box, away from the floor it stands on
        return np.sum((box_signed_distance(mesh.vertices, [person]) < 0.05) & (mesh.vertices[:, 2] > 0.1))

    assert on_person(tsdf_mesh(Frames(frames.depth, frames.intrinsic, frames.cam_c2w), cfg, progress=False)) > 100
    assert on_person(tsdf_mesh(frames, cfg, progress=False)) == 0
    with pytest.raises(ValueError, match="no surface"):
        tsdf_mesh(frames, TsdfConfig(depth_max=0.5), progress=False)
    with pytest.raises(ValueError, match="positive"):
        TsdfConfig(voxel_size=0.0)
    with pytest.raises(ValueError, match="piece_max_cell"):
        ColliderConfig(piece_min_cell=2.0, piece_max_cell=1.0)


def test_heightfield_reproduces_the_true_tops(field, clip):
    gx, gy = field.grid_xy()
    xy = np.c_[gx.reshape(-1), gy.reshape(-1)]
    heights = field.heights.reshape(-1)
    central = np.all(np.abs(xy - CENTER[:2]) < [2.0, 1.5], axis=1)  # well inside every camera's view
    truth = true_top(xy, clip.boxes)
    # A cell is flat when the truth is the same a resolution away in every direction.
    around = np.stack([true_top(xy + [dx, dy], clip.boxes)
                       for dx in (-RESOLUTION, 0, RESOLUTION) for dy in (-RESOLUTION, 0, RESOLUTION)])
    flat = np.ptp(around, axis=0) < 1e-9
    assert central.sum() > 1000 and (central & ~flat).sum() > 50
    err = heights - truth
    assert np.abs(err[central & flat]).max() < 0.5 * VOXEL
    # Near an edge, a grid point takes its cell's highest point: never lower than the truth at
    # the point (but where the mesh itself rounds a corner, within a voxel of it), never
    # higher than the truth within the cell.
    rounded = np.ptp([true_top(xy + [dx, dy], clip.boxes) for dx in (-VOXEL, 0, VOXEL) for dy in (-VOXEL, 0, VOXEL)],
                     axis=0) > 1e-9
    assert err[central & ~rounded].min() > -0.5 * VOXEL
    assert np.all(heights[central] < around[:, central].max(axis=0) + 0.5 * VOXEL)


def test_heightfield_clip_is_what_mujoco_collides(clips, field):
    directory = clips["heightfield"]
    assert (directory / "heightfield.bin").is_file()
    assert json.loads((directory / "primitives.json").read_text()) == []
    model = mujoco.MjModel.from_xml_path(str(directory / "scene.xml"))  # loads on its own
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    rng = np.random.default_rng(0)
    nrow, ncol = field.shape
    rows, cols = rng.integers(1, nrow - 1, 50), rng.integers(1, ncol - 1, 50)
    gx, gy = field.grid_xy()
    geom = np.zeros(1, np.int32)
    for r, c in zip(rows, cols):
        top = 5.0 - mujoco.mj_ray(model, data, np.array([gx[r, c], gy[r, c], 5.0]), np.array([0, 0, -1.0]),
                                  None, 1, -1, geom)
        assert top == pytest.approx(field.heights[r, c], abs=1e-4)  # rows along +y, columns along +x
    surface = scene_surface(directory / "scene.xml")
    assert len(surface.vertices) == nrow * ncol
    assert np.allclose(np.sort(surface.vertices[:, 2]), np.sort(field.heights.reshape(-1)), atol=1e-4)


def test_convex_pieces_are_convex_and_cover_the_mesh(pieces, mesh):
    assert all(p.is_convex for p in pieces)
    covered = np.zeros(len(mesh.vertices), bool)
    for p in pieces:
        covered |= inside(p, mesh.vertices, tol=1e-6)
    assert covered.all()
    assert len(pieces) < len(mesh.faces) / 50  # a decomposition, not a copy of the triangles


def test_convex_pieces_leave_free_space_free_where_the_dense_hull_fills_it(pieces, mesh, clip):
    rng = np.random.default_rng(0)
    points = CENTER + rng.uniform([-2.0, -1.2, -0.2], [2.0, 1.2, 0.6], (20000, 3))
    free = points[box_signed_distance(points, clip.boxes) > 0.08]  # farther from the truth than the mesh errs
    inside_pieces = np.zeros(len(free), bool)
    for p in pieces:
        inside_pieces |= inside(p, free)
    inside_hull = inside(mesh.convex_hull, free)
    assert inside_pieces.sum() == 0
    assert inside_hull.mean() > 0.3  # the raw mesh as one geom is not a faithful collider


@pytest.mark.parametrize("kind", ["heightfield", "convex_pieces", "dense_mesh"])
def test_baseline_clip_loads_alone_and_runs_in_the_env(clips, pieces, kind):
    directory = clips[kind]
    loaded = load_clip_dir(directory)
    assert loaded.scene_kind == kind and loaded.boxes == []
    scene = mujoco.MjModel.from_xml_path(str(directory / "scene.xml"))
    if kind == "convex_pieces":
        assert scene.ngeom == loaded.meta["num_pieces"] == len(pieces)
    env = CrispTrackEnv(clip=str(directory), scene_aware=True)
    scene_geoms = [g for g in range(env.model.ngeom) if env.model.geom_bodyid[g] == 0]
    assert len(scene_geoms) == scene.ngeom
    assert all(env.model.geom_contype[g] == SCENE_CONTYPE and env.model.geom_conaffinity[g] == SCENE_CONAFFINITY
               for g in scene_geoms)
    obs, _ = env.reset(seed=0, options={"start_frame": 0})
    assert obs["points"].shape == (128, 3) and np.all(np.isfinite(obs["points"]))
    for _ in range(5):
        obs, reward, terminated, _, _ = env.step(np.zeros(69, np.float32))
        assert np.isfinite(reward) and np.all(np.isfinite(env.data.qpos))
    if kind != "dense_mesh":
        assert not terminated
    venv = gym.make_vec("CrispTrack-v0", num_envs=2, vectorization_mode="vector_entry_point", clip=str(directory))
    venv.reset(seed=0)
    for _ in range(3):
        venv.step(np.zeros((2, 69)))
    assert np.all(np.isfinite(venv.unwrapped.batch.bind("qpos")[:]))
    venv.close()


def lowest_sole(env: CrispTrackEnv) -> float:
    """Lowest corner (z) of the feet's box geoms."""
    m, d = env.model, env.data
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    feet = [g for g in range(m.ngeom) if m.body(m.geom_bodyid[g]).name in FEET]
    return min((d.geom_xpos[g] + (signs * m.geom_size[g]) @ d.geom_xmat[g].reshape(3, 3).T)[:, 2].min() for g in feet)


@pytest.mark.parametrize("kind", ["boxes", "heightfield", "convex_pieces", "dense_mesh"])
def test_a_standing_humanoid_rests_on_the_floor_only_with_faithful_colliders(clips, kind):
    env = CrispTrackEnv(clip="stairs_up" if kind == "boxes" else str(clips[kind]))
    env.reset(seed=0, options={"start_frame": 0})  # feet on the floor (z = 0), PD holds the reference
    soles, pelvis_error, penetration = [], [], []
    for t in range(1, 16):
        env.step(np.zeros(69, np.float32))
        soles.append(lowest_sole(env))
        pelvis_error.append(abs(env.data.qpos[2] - env.task.reference.qpos[t, 2]))
        penetration.append(max([-c.dist for c in env.data.contact[:env.data.ncon]] + [0.0]))
    if kind == "dense_mesh":  # the floor is inside the mesh's convex hull: the feet are deep in it
        assert max(penetration) > 0.04
    else:
        assert min(soles) > -0.02 and max(penetration) < 0.02 and max(pelvis_error) < 0.03


def test_write_baseline_clips_records_counts_and_timings(tmp_path, clip):
    frames = orbit_frames(clip.boxes, views=6, width=120)
    cfg = TsdfConfig(voxel_size=0.06, depth_max=4.5, weight_threshold=1.0)
    written = write_baseline_clips(tmp_path, frames, clip.motion, "stairs", kinds=("heightfield", "dense_mesh"),
                                   tsdf=cfg, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stairs_dense_mesh", "stairs_heightfield"]
    for kind, directory in written.items():
        meta = json.loads((directory / "meta.json").read_text())
        assert meta["scene_kind"] == kind and meta["name"] == f"stairs_{kind}" and meta["num_primitives"] == 0
        assert meta["dense_triangles"] > 1000 and meta["tsdf"]["voxel_size"] == 0.06
        assert meta["timings"]["tsdf_s"] > 0 and meta["timings"]["convert_s"] >= 0
    with pytest.raises(ValueError, match="kinds"):
        write_baseline_clips(tmp_path, frames, clip.motion, "x", kinds=("voxels",), progress=False)


def test_an_interrupted_write_leaves_nothing(tmp_path, monkeypatch, clip, pieces):
    def interrupted(*args, **kwargs):  # the scene's files are written by then
        raise KeyboardInterrupt

    monkeypatch.setattr(Motion, "save", interrupted)
    with pytest.raises(KeyboardInterrupt):
        convex_pieces_clip(tmp_path / "pieces", pieces[:10], clip.motion)
    assert list(tmp_path.iterdir()) == []


def test_box_scenes_and_unknown_scene_kinds(tmp_path, sway_clip):
    assert load_clip_dir(sway_clip).scene_kind == "boxes"
    boxes = [Box(center=[0, 0, -0.05], half_size=[2, 1, 0.05]), Box(center=[1, 0, 0.2], half_size=[0.3, 0.2, 0.2])]
    write_scene_xml(boxes, tmp_path / "scene.xml")
    area = sum(8 * (b.half_size[0] * b.half_size[1] + b.half_size[1] * b.half_size[2]
                    + b.half_size[0] * b.half_size[2]) for b in boxes)
    assert scene_surface(tmp_path / "scene.xml").area == pytest.approx(area)
    meta = json.loads((sway_clip / "meta.json").read_text())
    bad = tmp_path / "bad"
    bad.mkdir()
    for f in ("scene.xml", "motion.npz", "primitives.json"):
        (bad / f).write_bytes((sway_clip / f).read_bytes())
    (bad / "meta.json").write_text(json.dumps({**meta, "scene_kind": "voxels"}))
    with pytest.raises(ValueError, match="scene_kind"):
        load_clip_dir(bad)
