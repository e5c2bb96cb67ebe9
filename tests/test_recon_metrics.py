"""Reconstruction metrics against hand-computable answers and a second method."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from crisp_gym.metrics import box_signed_distance
from crisp_gym.reconstruct.metrics import (
    chamfer_gt_to_recon,
    chamfer_recon_to_gt,
    chamfer_two_way,
    distance_to,
    non_penetration,
    primitive_count,
    sample_surface,
    support_coverage,
    surface_mesh,
)
from crisp_gym.reconstruct.raycast import box_mesh
from crisp_gym.scene import Box, floor_box
from crisp_gym.synth.scenes import StairsParams, stairs_boxes
from tests.conftest import sway_motion

SLAB = Box(center=[0.0, 0.0, -0.05], half_size=[1.0, 1.0, 0.05])  # top face: the 2 x 2 m square at z = 0
TOP = np.array([[-2.0, -2.0, -0.001], [2.0, 2.0, 0.001]])  # bounds around that top face only


def plate(z: float, half: float = 1.0, x0: float | None = None) -> Box:
    """A planar box whose surface (+z face) is at height ``z``, as planar fitting makes them."""
    lo = -half if x0 is None else x0
    return Box(center=[(lo + half) / 2, 0.0, z - 0.025], half_size=[(half - lo) / 2, half, 0.025])


def test_two_offset_planes_are_their_offset_apart():
    recon = [plate(0.05, half=1.5)]  # larger than the ground truth, so every GT point sees it above
    forward = chamfer_recon_to_gt([plate(0.05)], [SLAB])
    assert forward.mean == pytest.approx(0.05, abs=1e-5) and forward.median == pytest.approx(0.05, abs=1e-5)
    backward = chamfer_gt_to_recon(recon, [SLAB], bounds=TOP)
    assert backward.median == pytest.approx(0.05, abs=1e-5)
    assert backward.mean == pytest.approx(0.05, abs=1e-3)  # the 1 mm band of side faces inside the bounds
    # both surfaces inside the bounds: the GT top and the same square 5 cm above it
    band = np.array([[-2.0, -2.0, -0.001], [2.0, 2.0, 0.051]])
    assert chamfer_two_way([plate(0.05)], [SLAB], bounds=band) == pytest.approx(0.05, abs=1e-3)


def test_recon_faces_all_measures_the_back_of_the_boxes_too():
    # The whole surface of a 5 cm plate sitting on the slab's top: its top face is 5 cm above
    # the slab, its bottom face on it, its 5 cm sides within 0-5 cm: mean = (4 * 0.05 + 4 * 0 +
    # side area * 0.025) / total area.
    recon = [Box(center=[0.0, 0.0, 0.025], half_size=[1.0, 1.0, 0.025])]
    expected = (4.0 * 0.05 + 8.0 * 0.05 * 0.025) / (8.0 + 8.0 * 0.05)
    assert chamfer_recon_to_gt(recon, [SLAB], recon_faces="all").mean == pytest.approx(expected, abs=1e-3)
    assert chamfer_recon_to_gt(recon, [SLAB]).mean == pytest.approx(0.05, abs=1e-5)


def test_half_covered_top_has_half_coverage():
    # A surface over x >= 0 covers the slab's top there, and within 3 cm of its edge: 1.03 / 2.
    assert support_coverage([plate(0.0, x0=0.0)], [SLAB]) == pytest.approx(0.515, abs=0.015)
    assert support_coverage([plate(0.0)], [SLAB]) == 1.0
    assert support_coverage([plate(0.05)], [SLAB]) == 0.0  # 5 cm above: not within 3 cm


def test_support_surfaces_exclude_buried_faces_and_need_bounds_for_the_floor():
    block = Box(center=[0.0, 0.0, 0.25], half_size=[0.5, 0.5, 0.25])
    gt = [floor_box(), block]
    bounds = np.array([[-1.0, -1.0, -0.5], [1.0, 1.0, 1.0]])
    # Up-facing area in the bounds: the floor around the block (4 - 1 m²) and the block top (1 m²);
    # the floor under the block is buried, so the block's top alone covers a quarter.
    assert support_coverage([plate(0.5, half=0.5)], gt, bounds=bounds, spacing=0.01) == pytest.approx(0.25, abs=0.01)
    with pytest.raises(ValueError, match="bounds"):
        support_coverage([plate(0.5, half=0.5)], gt, spacing=0.01)  # the 40 m floor: 16 M points


def test_distances_match_the_exact_box_distance_outside_the_scene():
    gt = stairs_boxes(StairsParams(riser=0.15, tread=0.3, width=1.2, count=4, start=1.5, landing=1.4))
    rng = np.random.default_rng(0)
    points = rng.uniform([0.5, -1.5, 0.0], [4.5, 1.5, 1.5], size=(2000, 3))
    outside = box_signed_distance(points, gt)
    points = points[outside > 0]
    np.testing.assert_allclose(distance_to(points, surface_mesh(gt)), outside[outside > 0], atol=1e-5)


def test_ground_truth_against_itself_is_zero_and_fully_covered():
    gt = stairs_boxes(StairsParams(riser=0.15, tread=0.3, width=1.2, count=4, start=1.5, landing=1.4))
    bounds = np.array([[0.0, -1.5, -0.2], [5.0, 1.5, 1.0]])
    assert chamfer_recon_to_gt(gt, gt, bounds=bounds, recon_faces="all").p90 < 1e-5
    assert chamfer_gt_to_recon(gt, gt, bounds=bounds, recon_faces="all").p90 < 1e-5
    assert support_coverage(gt, gt, bounds=bounds) == 1.0


def test_union_surface_has_no_internal_faces():
    left = Box(center=[-0.5, 0.0, 0.5], half_size=[0.5, 0.5, 0.5])
    right = Box(center=[0.5, 0.0, 0.5], half_size=[0.5, 0.5, 0.5])
    mesh = surface_mesh([left, right])
    assert mesh.is_watertight
    assert mesh.area == pytest.approx(2 * (2 * 1 + 2 * 1 + 1 * 1))  # a 2 x 1 x 1 box: no shared face
    points, normals = sample_surface(mesh, 0.05)
    assert not np.any(np.abs(points[:, 0]) < 1e-6)  # nothing sampled on the shared face x = 0
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)


def test_a_mesh_reconstruction_measures_like_the_same_boxes():
    box = plate(0.05, half=0.8)
    as_boxes = chamfer_gt_to_recon([box], [SLAB], bounds=TOP, recon_faces="all")
    as_mesh = chamfer_gt_to_recon(box_mesh(box), [SLAB], bounds=TOP)
    assert as_mesh == as_boxes
    assert primitive_count(box_mesh(box)) == 12 and primitive_count([box, SLAB]) == 2


def test_non_penetration_of_a_grounded_motion():
    motion = sway_motion(20)  # grounded: the soles touch z = 0
    on_floor = non_penetration([floor_box()], motion)
    assert on_floor.vertex_score == 1.0 and on_floor.frame_score == 1.0 and on_floor.max_depth < 0.005
    raised = non_penetration([floor_box(height=0.1, thickness=1.0)], motion)  # the floor 10 cm too high
    assert raised.frame_score == 0.0 and raised.max_depth == pytest.approx(0.1, abs=0.005)
    assert 0.5 < raised.vertex_score < 0.99  # the feet and shins are in it, the rest is not
    as_mesh = non_penetration(box_mesh(floor_box(height=0.1, thickness=1.0)), motion)
    assert as_mesh.vertex_score == pytest.approx(raised.vertex_score, abs=1e-6)


@pytest.mark.parametrize("call, message", [
    (lambda: chamfer_recon_to_gt([], [SLAB]), "non-empty list"),
    (lambda: chamfer_recon_to_gt([plate(0.0)], [SLAB], recon_faces="front"), "faces"),
    (lambda: chamfer_gt_to_recon([plate(0.0)], [SLAB], bounds=[[0, 0, 0], [0, 1, 1]]), "bounds"),
    (lambda: chamfer_gt_to_recon([plate(0.0)], [SLAB], bounds=[[5, 5, 5], [6, 6, 6]]), "empty"),
    (lambda: support_coverage([plate(0.0)], [SLAB], distance=0.0), "distance"),
    (lambda: sample_surface(surface_mesh([SLAB]), spacing=0.0), "spacing"),
    (lambda: non_penetration(trimesh.Trimesh(*_open_mesh()), sway_motion(4)), "watertight"),
    (lambda: non_penetration([SLAB], "motion.npz"), "Motion"),
])
def test_bad_input_is_rejected(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def _open_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A single square: not closed."""
    return np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float), np.array([[0, 1, 2], [0, 2, 3]])
