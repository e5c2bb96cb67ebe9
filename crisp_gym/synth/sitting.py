"""Sitting down on a box seat and rising from it: the seated pelvis height solved against the
humanoid's geometry, the perched pose over the feet, and the seat contacts."""

from __future__ import annotations

import mujoco
import numpy as np

from crisp_gym.humanoid import FEET
from crisp_gym.metrics import scene_model
from crisp_gym.motion import Motion
from crisp_gym.scene import Box
from crisp_gym.synth.gait import PELVIS_AHEAD, GaitParams, MotionPlan
from crisp_gym.synth.ik import PoseFrames, solve_joints
from crisp_gym.synth.scenes import SeatParams, seat_boxes
from crisp_gym.synth.skeleton import SIDE, Skeleton

SEAT_BODIES = ("Pelvis", "L_Hip", "R_Hip")
_SEAT_CONTACT_TOLERANCE = 0.005  # m: a thigh this close to the seat counts as resting on it
_SEAT_OFF_SHARE = 0.45  # of a rise (a descent): on the seat, leaning, before (after) the feet bear the body
_RISE_COM_MARGIN = -0.02  # m: centre of mass in front of the heels (negative: behind) perched and leaning
_SEAT_EDGE_CLEARANCE = 0.03  # m: the seated pelvis stays this far behind the seat's front
_SEATED_SPINE = -0.15  # rad: the seated trunk leans back a little, its weight on the seat
_PERCH_SCAN_DEPTH = 0.22  # m behind the seat's front: where the search for a perched pelvis starts


def _seated_height(seat: SeatParams, feet_s: float, pelvis_s: float, pitch: float, gait: GaitParams,
                   skel: Skeleton) -> float:
    """Pelvis height at which the thighs rest on the seat (1 mm compression), by bisection on
    the real humanoid geometry posed by the same IK as the motion."""
    seat_model, seat_geom = _seat_model(seat, skel.stature)
    thighs = [seat_model.geom(g).id for g in range(seat_model.ngeom)
              if seat_model.geom_bodyid[g] in {seat_model.body("L_Hip").id, seat_model.body("R_Hip").id,
                                               seat_model.body("Pelvis").id}]
    data = mujoco.MjData(seat_model)

    def gap(z: float) -> float:
        frames = _standing_frames(np.full(2, pelvis_s), np.full(2, z), np.full(2, pitch), feet_s, gait, skel)
        motion = solve_joints(frames, skel, gait, 30.0, skel.leg * 0.9999)
        data.qpos[:] = motion.qpos()[0]
        mujoco.mj_kinematics(seat_model, data)
        return min(mujoco.mj_geomDistance(seat_model, data, g, seat_geom, 0.5, None) for g in thighs)

    # Scan up from the seat (the gap is not monotonic far above it, where the straightening
    # legs swing the knees back into the seat's front), then bisect to the touching height.
    lo = seat.height
    for hi in seat.height + np.arange(0.05, 0.40, 0.01):
        if gap(hi) >= -0.001:
            break
        lo = hi
    else:
        raise RuntimeError(f"found no seated pose on a {seat.height:.2f} m seat for this humanoid")
    for _ in range(30):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if gap(mid) < -0.001 else (lo, mid)
    return hi


def _seat_model(seat: SeatParams, stature: float) -> tuple[mujoco.MjModel, int]:
    """The humanoid with the seat box alone, and the seat's geom id."""
    model = scene_model([b for b in seat_boxes(seat) if b.name == "seat"], stature)
    return model, model.geom("seat").id


def _standing_frames(pelvis_s: np.ndarray, pelvis_z: np.ndarray, pitch: np.ndarray, feet_s: float,
                     gait: GaitParams, skel: Skeleton, spine: float = 0.0, arms: float = 0.0) -> PoseFrames:
    """Frames with both feet planted at ``feet_s`` on the floor of a straight path."""
    n = len(pelvis_s)
    zeros = np.zeros(n)
    ankle = np.zeros((n, 2, 3))
    ankle[..., 0] = feet_s
    ankle[..., 1] = SIDE * gait.step_width / 2
    ankle[..., 2] = skel.ankle_height
    return PoseFrames(pelvis_xy=np.stack([pelvis_s, zeros], axis=1), pelvis_z=pelvis_z, yaw=zeros, pitch=pitch,
                   roll=zeros, spine=np.full(n, spine), arms=np.full(n, arms), ankle=ankle,
                   foot_yaw=np.tile(SIDE * gait.toe_out, (n, 1)), foot_pitch=np.zeros((n, 2)),
                   foot_s=np.full((n, 2), feet_s),
                   pelvis_s=pelvis_s, stance=np.ones((n, 2), dtype=bool), phase=np.zeros((n, 2)))


def add_sit(plan: MotionPlan, seat: SeatParams, gait: GaitParams, skel: Skeleton, rng: np.random.Generator) -> float:
    """Stand, sit down on the seat behind, stay, stand up; feet planted at s = 0. Returns the end time.

    The trunk's forward lean comes from the spine while the pelvis tilts back (as it does when
    sitting): this keeps the hips' flexion below 90 degrees, where their x-y-z hinges are
    singular and ab/adduction would swing wildly.

    The body lowers itself onto, stays on, and rises from the front of the seat, where under
    the lean the centre of mass is just behind the heels (:func:`_perched_position`,
    :data:`_RISE_COM_MARGIN`; the pelvis already moves forward as the thighs leave the seat).
    Sitting straight back onto the seat and rising from it put the centre of mass 9-10 cm
    behind the heels (the first generator): no ground force lowers or lifts a body from there
    without it falling. Perching further forward hides the seat from the kinematic contact cue,
    which needs the seated centre of mass clearly behind the feet (docs/synthetic_clips.md).
    Sliding back on the seat and forward again before rising (the second) asked a simulated
    body to scoot 15 cm along a seat that holds it by friction: policies learned to skip the
    slide, and from a seated start they could not rise.
    """
    stand = skel.pelvis_height - 0.012
    seated_pitch = -0.2
    down, hold, up = rng.uniform(1.4, 1.8), rng.uniform(1.2, 1.8), rng.uniform(1.4, 1.8)
    lean_down, lean_up = rng.uniform(1.05, 1.2), rng.uniform(1.05, 1.2)
    t1 = 0.6
    t2, t3 = t1 + down, t1 + down + hold
    t4 = t3 + up
    # The least lean needs the pelvis furthest forward; the other lean is then over the feet too.
    seated_s, z_seat = _perched_position(seat, seated_pitch, min(lean_down, lean_up), gait, skel)
    plan.pose(0.0, PELVIS_AHEAD, 0.0, stand)
    plan.pose(t1, PELVIS_AHEAD, 0.0, stand)
    # Down: lean, lower onto the seat's front, then sit up.
    touch = t1 + (1.0 - _SEAT_OFF_SHARE) * down
    plan.key("spine", t1 + 0.6 * (touch - t1), lean_down)
    plan.key("arms", t1 + 0.6 * (touch - t1), 0.6 * lean_down)
    plan.pose(touch, seated_s, 0.0, z_seat, pitch=seated_pitch, spine=lean_down, arms=0.6 * lean_down)
    plan.pose(t2, seated_s, 0.0, z_seat, pitch=seated_pitch, spine=_SEATED_SPINE)
    plan.pose(t3, seated_s, 0.0, z_seat, pitch=seated_pitch, spine=_SEATED_SPINE)
    # Up: lean forward on the seat, then rise while moving forward.
    seat_off = t3 + _SEAT_OFF_SHARE * up
    plan.pose(seat_off, seated_s, 0.0, z_seat, pitch=seated_pitch, spine=lean_up, arms=0.6 * lean_up)
    plan.pose(t4, PELVIS_AHEAD, 0.0, stand)
    return t4


def _perched_position(seat: SeatParams, pitch: float, lean: float, gait: GaitParams,
                      skel: Skeleton) -> tuple[float, float]:
    """The pelvis (s, z) on the seat from which the body can rise (and onto which it can lower
    itself) with the spine leaning by ``lean``.

    The first position forward (1 cm steps, the pelvis kept :data:`_SEAT_EDGE_CLEARANCE` behind
    the seat's front) that puts the centre of mass :data:`_RISE_COM_MARGIN` in front of the heels.
    """
    model, _ = _seat_model(seat, skel.stature)
    data = mujoco.MjData(model)
    feet = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX
            and model.body(model.geom_bodyid[g]).name in FEET]
    for pelvis_s in np.arange(seat.front - _PERCH_SCAN_DEPTH, seat.front - _SEAT_EDGE_CLEARANCE + 1e-9, 0.01):
        z = _seated_height(seat, 0.0, pelvis_s, pitch, gait, skel)
        frames = _standing_frames(np.full(2, pelvis_s), np.full(2, z), np.full(2, pitch), 0.0, gait, skel,
                                  spine=lean, arms=0.6 * lean)
        data.qpos[:] = solve_joints(frames, skel, gait, 30.0, skel.leg * 0.9999).qpos()[0]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        heels = min((data.geom_xpos[g] - np.abs(data.geom_xmat[g].reshape(3, 3)) @ model.geom_size[g])[0]
                    for g in feet)
        if data.subtree_com[model.body("Pelvis").id][0] - heels >= _RISE_COM_MARGIN:
            return float(pelvis_s), z
    raise RuntimeError(f"no pelvis position on this seat (front at {seat.front:.2f} m) puts the centre of "
                       f"mass over the feet")


def seat_contacts(motion: Motion, boxes: list[Box], stature: float) -> np.ndarray:
    """(T,) frames where the thighs are within :data:`_SEAT_CONTACT_TOLERANCE` of the seat."""
    model = scene_model([b for b in boxes if b.name == "seat"], stature)
    data = mujoco.MjData(model)
    seat = model.geom("seat").id
    thighs = [g for g in range(model.ngeom)
              if model.geom_bodyid[g] in {model.body("L_Hip").id, model.body("R_Hip").id}]
    qpos = motion.qpos()
    out = np.zeros(motion.num_frames, dtype=bool)
    for k in range(motion.num_frames):
        data.qpos[:] = qpos[k]
        mujoco.mj_kinematics(model, data)
        out[k] = min(mujoco.mj_geomDistance(model, data, g, seat, 0.1, None) for g in thighs) \
            < _SEAT_CONTACT_TOLERANCE
    return out
