"""Video landmarks → humanoid motion: known poses come back, leg IK keeps bone lengths, sparse surfaces."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES, build_humanoid
from crisp_gym.motion import compute_kinematics
from crisp_gym.reconstruct.landmarks import (
    body_rotations,
    fill_gaps,
    landmarks_to_motion,
    leg_lengths,
    with_leg_lengths,
)
from crisp_gym.reconstruct.person import LANDMARKS, landmark
from crisp_gym.reconstruct.sparse_planes import SparsePlaneConfig, ground_box, level_tops, seat_surface
from crisp_gym.reconstruct.video import adjust_legs
from crisp_gym.registry import load_clip

# Landmark -> (body whose frame carries it, offset in that body's frame): where MediaPipe's
# landmarks sit on our skeleton, so a posed humanoid gives the landmarks a video of it would.
_ON_BODY = {
    "hip": ("Hip", (0, 0, 0)), "knee": ("Knee", (0, 0, 0)), "ankle": ("Ankle", (0, 0, 0)),
    "heel": ("Ankle", (-0.05, 0, -0.05)), "foot_index": ("Toe", (0.04, 0, -0.01)),
    "shoulder": ("Shoulder", (0, 0, 0)), "elbow": ("Elbow", (0, 0, 0)), "wrist": ("Wrist", (0, 0, 0)),
    "index": ("Hand", (0.02, 0.06, 0)), "pinky": ("Hand", (-0.02, 0.06, 0)), "thumb": ("Hand", (0.03, 0.03, 0)),
}


def landmarks_of(motion, model) -> np.ndarray:
    """(T, 33, 3) landmarks of the humanoid posed by ``motion``."""
    kin = compute_kinematics(motion, model)
    rot = Rotation.from_quat(kin.body_quat.reshape(-1, 4), scalar_first=True).as_matrix()
    rot = rot.reshape(motion.num_frames, len(BODY_NAMES), 3, 3)
    at = lambda body, offset: kin.body_pos[:, BODY_NAMES.index(body)] + rot[:, BODY_NAMES.index(body)] @ np.asarray(
        offset, float)  # noqa: E731
    out = np.zeros((motion.num_frames, len(LANDMARKS), 3))
    for i, name in enumerate(LANDMARKS):
        side, _, part = name.partition("_")
        if side in ("left", "right") and part in _ON_BODY:
            body, offset = _ON_BODY[part]
            mirror = np.array([1, 1 if side == "left" else -1, 1])
            out[:, i] = at(f"{side[0].upper()}_{body}", mirror * offset)
        else:  # the face: ears beside the head, the nose in front, the rest near the nose
            face = {"left_ear": (0, 0.07, 0.05), "right_ear": (0, -0.07, 0.05)}
            out[:, i] = at("Head", face.get(name, (0.1, 0, 0.035)))
    return out


@pytest.fixture(scope="module")
def model():
    return build_humanoid()


@pytest.mark.parametrize("clip", ["flat_walk", "chair_sit", "stairs_up"])
def test_a_posed_humanoid_comes_back(clip, model):
    """Landmarks of the humanoid posed by a bundled motion retarget to the same body positions."""
    motion = load_clip(clip).motion
    points = landmarks_of(motion, model)
    result = landmarks_to_motion(points, motion.fps, model=model, smoothing_seconds=0.0, shift=False)
    got = compute_kinematics(result.motion, model).body_pos
    want = compute_kinematics(motion, model).body_pos
    error = np.linalg.norm(got - want, axis=2)  # (T, 24)
    legs = [BODY_NAMES.index(b) for b in ("L_Knee", "R_Knee", "L_Ankle", "R_Ankle")]
    assert np.median(error) < 0.02
    assert np.percentile(error[:, legs], 95) < 0.04


def test_rest_pose_gives_zero_hinges(model):
    """The T-pose's landmarks are the rest pose: every hinge near zero except where the synthetic
    face and hand landmarks are off-axis (neck, head, hands)."""
    from crisp_gym.motion import Motion

    rest = Motion(fps=30, root_pos=np.tile([0, 0, 1.0], (3, 1)), root_quat=np.tile([1.0, 0, 0, 0], (3, 1)),
                  dof_pos=np.zeros((3, 69)))
    rotations = body_rotations(landmarks_of(rest, model))
    for body in ("Pelvis", "L_Hip", "R_Knee", "L_Shoulder", "R_Elbow", "Chest"):
        angle = Rotation.from_matrix(rotations[:, BODY_NAMES.index(body)]).magnitude()
        assert np.all(np.rad2deg(angle) < 1.0), body


def test_gaps_are_interpolated():
    points = np.random.default_rng(0).normal(size=(10, 33, 3))
    holed = points.copy()
    holed[3:5] = np.nan
    filled = fill_gaps(holed)
    np.testing.assert_allclose(filled[3], points[2] + (points[5] - points[2]) / 3)
    with pytest.raises(ValueError, match="no frame"):
        fill_gaps(np.full((4, 33, 3), np.nan))


def test_leg_ik_keeps_lengths_and_reaches_the_feet(model):
    motion = load_clip("chair_sit").motion
    thigh, shin = leg_lengths(model)
    points = with_leg_lengths(landmarks_of(motion, model), thigh, shin)
    drop = np.full(motion.num_frames, 0.1)
    lift = np.full((motion.num_frames, 2), -0.02)
    moved = adjust_legs(points, drop, lift, thigh, shin)
    for side, k in (("left", 0), ("right", 1)):
        hip, knee, ankle = (moved[:, landmark(f"{side}_{j}")] for j in ("hip", "knee", "ankle"))
        np.testing.assert_allclose(np.linalg.norm(knee - hip, axis=1), thigh, atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(ankle - knee, axis=1), shin, atol=1e-6)
        np.testing.assert_allclose(ankle, points[:, landmark(f"{side}_ankle")] + [0, 0, -0.02])
        np.testing.assert_allclose(hip, points[:, landmark(f"{side}_hip")] - [0, 0, 0.1])


def _slab(rng, n, x, y, z, noise=0.005):
    return np.c_[rng.uniform(*x, n), rng.uniform(*y, n), z + rng.normal(0, noise, n)]


def test_sparse_surfaces_find_ground_seat_and_table_but_not_a_bush():
    rng = np.random.default_rng(1)
    ground = _slab(rng, 2000, (-2, 2), (-2, 2), 0.0)
    log_top = _slab(rng, 60, (0.5, 1.5), (0.9, 1.1), 0.25)
    log_side = np.c_[rng.uniform(0.5, 1.5, 80), np.full(80, 0.9), rng.uniform(0, 0.25, 80)]
    table = _slab(rng, 150, (-1.5, -0.9), (-1.5, -0.9), 0.72)
    bush = np.c_[rng.normal(-1.0, 0.2, (400, 2)) + [0, 2.0], rng.uniform(0.0, 1.0, 400)]
    points = np.concatenate([ground, log_top, log_side, table, bush])
    path = np.c_[np.linspace(-1, 1, 50), np.zeros(50), np.full(50, 0.9)]

    floor = ground_box(points, path)
    assert floor.center[2] + floor.half_size[2] == pytest.approx(0.0)
    local = (path - floor.center) @ floor.rotation
    assert np.all(np.abs(local[:, :2]) <= floor.half_size[:2])

    # A seated body's underside 8 cm above the log, over a third of its top.
    patch = np.c_[rng.uniform(0.8, 1.1, 9), rng.uniform(0.95, 1.05, 9), np.full(9, 0.33)]
    seat = seat_surface(points, patch, max_drop=0.35)
    assert seat is not None and seat.center[2] + seat.half_size[2] == pytest.approx(0.25, abs=0.01)
    assert seat_surface(points, patch + [0, 0, 1.0], max_drop=0.35) is None  # nothing within reach below

    # Structure from motion's points scatter ±3 cm about the top, with a few strays above: the
    # top is where they are densest, not the upper edge of their scatter.
    noisy = np.concatenate([ground, _slab(rng, 150, (0.5, 1.5), (0.9, 1.1), 0.25, noise=0.03),
                            _slab(rng, 12, (0.5, 1.5), (0.9, 1.1), 0.36, noise=0.01)])
    seat = seat_surface(noisy, patch + [0, 0, 0.1], max_drop=0.35)
    assert seat is not None and seat.center[2] + seat.half_size[2] == pytest.approx(0.25, abs=0.015)

    tops = level_tops(points, path, SparsePlaneConfig(radius=3.0))
    heights = sorted(round(b.center[2] + b.half_size[2], 2) for b in tops)
    assert any(abs(h - 0.72) < 0.02 for h in heights), heights
    bush_xy = np.array([-1.0, 2.0])
    assert not any(np.linalg.norm(b.center[:2] - bush_xy) < 0.4 for b in tops), "a slice of the bush became a surface"
