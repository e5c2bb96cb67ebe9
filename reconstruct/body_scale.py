"""The person's body as the plain video's metre stick: how large it is, and a second measure of the scale.

The video path's scale (:func:`reconstruct.video.metric_scale`) places MediaPipe's metric
landmarks by PnP and compares their depth at the lowest foot with the depth where that foot's
ray meets the scene's floor. PnP's depth grows with the focal length, and bundle adjustment
refines a handheld clip's focal length by 25-40 % (on the bundled real video, from 672 to
841-922 px); but a focal length that fits the pixels comes with depths stretched to match, and
the floor recedes with the person: on a synthetic scene solved with a focal length 25 or 40 %
too long, the scale comes out within 3 % and the camera's height within 2 cm (tested). What the
scale does rest on is the body's size, so:

* **the body's size** (:func:`leg_length`, :func:`implied_stature`, :func:`stature_factor`):
  MediaPipe's world landmarks have a body size of their own (on the bundled real video, hip to
  ankle 0.74 m: the legs of a 1.51 m person in the humanoid's anthropometric table, where the
  humanoid's 1.70 m have 0.83 m). When the person's stature is known, the scene is scaled so that
  their legs have that stature's length;
* **a second measure** (:func:`ground_metrology`): single-view metrology against the scene's
  floor, by heights where the scale measures depths. The lowest foot's ray meets the floor; the
  hips' ray passes over that point (offset by the landmarks' horizontal hip-to-foot offset); the
  hips' height found there is compared with the landmarks' own hip height above that foot. The
  ratio is 1 when the scene and the body agree and 1.25 when the scene is 1.25 times too large for
  the body (tested); on the bundled real video it is 0.95-0.98. It rests on the body's size as the
  scale does, but not on the depths: a floor or a scale that went wrong shows in it.
"""

from __future__ import annotations

import numpy as np

from crisp_gym.humanoid import BODY_NAMES, default_rest_joints
from crisp_gym.reconstruct.person import PersonTrack, landmark

_HIPS = [landmark("left_hip"), landmark("right_hip")]


def leg_length(track: PersonTrack, min_visibility: float = 0.5) -> float:
    """Median hip-to-ankle length (thigh plus shin) of MediaPipe's world landmarks, metres, over
    the legs seen with at least ``min_visibility`` at the hip, knee and ankle (both legs pooled)."""
    lengths = []
    for side in ("left", "right"):
        hip, knee, ankle = (landmark(f"{side}_{j}") for j in ("hip", "knee", "ankle"))
        seen = track.found & (track.visibility[:, [hip, knee, ankle]].min(axis=1) >= min_visibility)
        w = track.world[seen]
        thigh, shin = w[:, hip] - w[:, knee], w[:, knee] - w[:, ankle]
        lengths.append(np.linalg.norm(thigh, axis=1) + np.linalg.norm(shin, axis=1))
    lengths = np.concatenate(lengths)
    if len(lengths) < 3:
        raise ValueError("the legs are seen in too few frames to measure the person's size")
    return float(np.median(lengths))


def stature_leg_length(height: float) -> float:
    """Hip joint to ankle joint, metres, of a person ``height`` metres tall in the humanoid's
    anthropometric table (0.49 of the stature)."""
    rest = default_rest_joints(height)
    return float(rest[BODY_NAMES.index("L_Hip"), 2] - rest[BODY_NAMES.index("L_Ankle"), 2])


def stature_factor(track: PersonTrack, height: float, min_visibility: float = 0.5) -> float:
    """How much larger a person ``height`` metres tall is than MediaPipe's landmarks of them (by leg length)."""
    return stature_leg_length(height) / leg_length(track, min_visibility)


def implied_stature(track: PersonTrack, min_visibility: float = 0.5) -> float:
    """The stature, metres, whose legs in the anthropometric table are as long as MediaPipe's landmarks'."""
    return leg_length(track, min_visibility) / stature_leg_length(1.0)


def ground_metrology(pixels: np.ndarray, landmarks: np.ndarray, feet: np.ndarray, cam_c2w: np.ndarray,
                     intrinsic: np.ndarray, min_height: float = 0.3) -> np.ndarray:
    """Per frame, the hips' height above the lowest foot measured by rays against the floor over
    that measured by the landmarks (see the module docstring; 1 when the scale is right).

    Args:
        pixels: (T, 33, 2) landmark pixels.
        landmarks: (T, 33, 3) metric landmarks placed in the floor frame (floor z = 0, z up).
        feet: indices of the landmarks a foot's lowest point is taken from.
        cam_c2w: (T, 4, 4) camera-to-floor-frame poses (OpenCV camera), in the same units.
        intrinsic: (3, 3) pinhole matrix.
        min_height: m; frames whose hips are less than this above the foot (a deep crouch) are left
            out: the ratio of two small heights is noise.

    Returns:
        (K,) ratios over the frames where the foot's ray meets the floor in front of the camera.
    """
    inverse = np.linalg.inv(intrinsic)
    up = np.array([0.0, 0.0, 1.0])
    ratios = []
    for k in range(len(pixels)):
        if not np.isfinite(pixels[k]).all() or not np.isfinite(landmarks[k]).all():
            continue
        foot = feet[int(np.argmax(pixels[k, feet, 1]))]  # lowest in the image: the one on the floor
        rotation, centre = cam_c2w[k, :3, :3], cam_c2w[k, :3, 3]
        to_foot = rotation @ inverse @ [*pixels[k, foot], 1.0]
        if to_foot[2] >= 0 or centre[2] <= 0:
            continue  # the ray never comes down to the floor
        on_floor = centre - centre[2] / to_foot[2] * to_foot
        hips = landmarks[k, _HIPS].mean(axis=0)
        body_height = hips[2] - landmarks[k, foot, 2]
        if body_height < min_height:
            continue
        under_hips = on_floor + np.r_[(hips - landmarks[k, foot])[:2], 0.0]
        to_hips = rotation @ inverse @ [*pixels[k, _HIPS].mean(axis=0), 1.0]
        # The hips' ray and the vertical through ``under_hips``: their closest points.
        a = np.array([[to_hips @ to_hips, -to_hips @ up], [to_hips @ up, -1.0]])
        b = np.array([(under_hips - centre) @ to_hips, (under_hips - centre) @ up])
        if abs(np.linalg.det(a)) < 1e-12:
            continue
        along, _ = np.linalg.solve(a, b)
        ratios.append((centre + along * to_hips)[2] / body_height)
    return np.asarray(ratios)
