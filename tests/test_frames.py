"""Frames validation and the depth renderer agree on geometry (a known box scene)."""

from __future__ import annotations

import numpy as np
import pytest

from crisp_gym.geometry import intrinsic_from_fov, look_at
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.raycast import DepthRenderer, box_mesh
from crisp_gym.scene import Box, floor_box


def _render_scene():
    step = Box(center=[2.0, 0.0, 0.25], half_size=[0.25, 0.5, 0.25])
    renderer = DepthRenderer([box_mesh(floor_box(thickness=0.1)), box_mesh(step)])
    k = intrinsic_from_fov(64, 48, 60.0)
    pose = look_at([0.0, 0.0, 1.5], [2.0, 0.0, 0.3])
    depth, ids = renderer.render(k, pose, 64, 48)
    return Frames(depth[None], k, pose[None]), ids


def test_rendered_points_lie_on_the_surfaces_they_hit():
    frames, ids = _render_scene()
    points = frames.world_points(0)
    assert set(np.unique(ids)) == {0, 1}
    np.testing.assert_allclose(points[ids == 0][:, 2], 0.0, atol=1e-5)  # the floor's top is z = 0
    on_step = points[ids == 1]
    # every point the camera sees on the step is on its top (z = 0.5) or its front face (x = 1.75)
    on_face = np.minimum(np.abs(on_step[:, 2] - 0.5), np.abs(on_step[:, 0] - 1.75))
    assert on_face.max() < 1e-5


def test_scaling_keeps_world_points_consistent():
    frames, ids = _render_scene()
    scaled = frames.scaled(2.0)
    np.testing.assert_allclose(scaled.world_points(0)[ids >= 0], 2.0 * frames.world_points(0)[ids >= 0], atol=1e-5)


@pytest.mark.parametrize("kwargs, message", [
    ({"depth": np.ones((0, 4, 4))}, "zero frames"),
    ({"depth": np.ones((4, 4))}, r"\(T, H, W\)"),
    ({"depth": np.full((1, 4, 4), np.nan)}, "no valid"),
    ({"cam_c2w": np.tile(np.eye(4), (2, 1, 1))}, "match depth"),
    ({"intrinsic": np.zeros((3, 3))}, "pinhole"),
    ({"person_mask": np.ones((1, 3, 4))}, "person_mask"),
])
def test_bad_input_is_rejected_with_a_clear_message(kwargs, message):
    args = {"depth": np.ones((1, 4, 4)), "intrinsic": intrinsic_from_fov(4, 4, 60.0),
            "cam_c2w": np.eye(4)[None]} | kwargs
    with pytest.raises(ValueError, match=message):
        Frames(**args)


def test_nan_depth_becomes_missing():
    depth = np.ones((1, 4, 4))
    depth[0, 1, 1] = np.nan
    frames = Frames(depth, intrinsic_from_fov(4, 4, 60.0), np.eye(4)[None])
    assert not frames.valid[0, 1, 1] and frames.valid.sum() == 15
