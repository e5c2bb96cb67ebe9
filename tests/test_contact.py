"""Contact sources, the temporal–kinematic filter and support completion, against the
synthetic clips' ground truth (their boxes and ``motion.contacts``)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, build_humanoid
from crisp_gym.metrics import support_tops
from crisp_gym.motion import Motion, compute_kinematics, ground
from crisp_gym.reconstruct.contact import (
    NUM_SMPL_VERTICES,
    PART_OF,
    PARTS,
    CompletionConfig,
    Contact,
    ContactEvidence,
    FilterConfig,
    body_geometry,
    complete_support,
    contact_labels,
    filter_contacts,
    kinematic_contacts,
    load_external_contacts,
    save_contacts,
)  # fmt: skip
from crisp_gym.registry import load_clip
from crisp_gym.scene import Box, floor_box
from crisp_gym.smpl import SMPL_JOINT_NAMES, SMPL_TO_BODY
from crisp_gym.synth.clips import make_clip

SURFACE_TOLERANCE = 0.05  # m: the bound on a contact box's top
SUPPORT_NAMES = ("seat", "platform", "landing")  # boxes a person rests on (besides step_*)


@lru_cache(maxsize=None)
def _bundled(name: str):
    clip = load_clip(name)
    return clip.boxes, clip.motion


@lru_cache(maxsize=None)
def _made(kind: str, seed: int):
    boxes, motion, _ = make_clip(kind, seed)
    return boxes, motion


def _kinematic(motion: Motion):
    geo = body_geometry(motion)
    return geo, filter_contacts(kinematic_contacts(motion, geometry=geo), motion, geometry=geo)


def _is_support(box: Box) -> bool:
    return box.name in SUPPORT_NAMES or (box.name or "").startswith("step_")


def _hold(motion: Motion, frame: int, count: int) -> Motion:
    """``motion`` frozen at ``frame`` for ``count`` extra frames (contacts included)."""
    idx = np.r_[np.arange(frame + 1), np.full(count, frame), np.arange(frame + 1, motion.num_frames)]
    return Motion(fps=motion.fps, root_pos=motion.root_pos[idx], root_quat=motion.root_quat[idx],
                  dof_pos=motion.dof_pos[idx], contacts=motion.contacts[idx])


def _precision_recall(pred: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    tp = np.sum(pred & truth)
    return tp / max(pred.sum(), 1), tp / max(truth.sum(), 1)


# --------------------------------------------------------------------------- kinematic source


@pytest.mark.parametrize("name", ["chair_sit", "platform_step", "stairs_up", "flat_walk"])
def test_kinematic_contacts_agree_with_ground_truth(name):
    _, motion = _bundled(name)
    _, contacts = _kinematic(motion)
    labels = contact_labels(contacts, motion.num_frames)
    for part in ("foot", "seat"):
        idx = [BODY_NAMES.index(b) for b in PARTS[part]]
        truth = motion.contacts[:, idx]
        precision, recall = _precision_recall(labels[:, idx], truth)
        if truth.any():
            # GT marks a foot from 5 mm off its support; a settling sole a little higher, or a
            # seated pelvis still slowing down, is the difference. The seat cue is a centre of
            # mass that cannot balance on the feet: while the sitter lowers itself onto and
            # lifts itself from the seat's front (~0.7 s each way) it keeps it over the feet, as
            # a body must, so the seat's part in those frames is invisible to kinematics.
            assert precision >= 0.9 and recall >= (0.95 if part == "foot" else 0.75), (part, precision, recall)
        else:
            assert not labels[:, idx].any(), f"{part} contacts where the clip has none"
    # No clip leans on its hands or back.
    assert all(c.part in ("foot", "seat") for c in contacts)
    # Each contact sits at its window's most stationary frame, inside the window.
    assert all(c.start <= c.frame < c.stop and c.part == PART_OF[c.body] for c in contacts)


def _crouch(lean_deg: float, frames: int = 30) -> Motion:
    """Thighs level, shanks 35° forward, heels down, trunk leaning ``lean_deg`` forward; held still."""
    dof = np.zeros((frames, len(DOF_NAMES)))
    for side in "LR":
        dof[:, DOF_NAMES.index(f"{side}_Hip_y")] = np.radians(-90 - lean_deg)
        dof[:, DOF_NAMES.index(f"{side}_Knee_y")] = np.radians(125)
        dof[:, DOF_NAMES.index(f"{side}_Ankle_y")] = np.radians(-35)
    dof[:, DOF_NAMES.index("L_Shoulder_x")], dof[:, DOF_NAMES.index("R_Shoulder_x")] = -1.2, 1.2
    quat = Rotation.from_euler("y", lean_deg, degrees=True).as_quat(scalar_first=True)
    motion = Motion(fps=30.0, root_pos=np.tile([0.0, 0.0, 1.0], (frames, 1)), root_quat=np.tile(quat, (frames, 1)),
                    dof_pos=dof)
    return ground(motion, build_humanoid())


def test_balanced_squat_is_not_sitting():
    """The same low pelvis sits only when the centre of mass is behind the feet."""
    pelvis = BODY_NAMES.index("Pelvis")
    squat, sit = _crouch(45.0), _crouch(-10.0)  # a squat leans forward; a sitter leans back
    for motion, seated in ((squat, False), (sit, True)):
        geo = body_geometry(motion)
        assert geo.body_pos[0, pelvis, 2] < 0.55 * geo.standing_pelvis  # as low as a chair sit
        prob = kinematic_contacts(motion, geometry=geo).prob
        assert np.all(prob[:, [BODY_NAMES.index(b) for b in PARTS["foot"]]] == 1.0)
        assert (prob[:, pelvis].min() > 0.5) if seated else (prob[:, pelvis].max() == 0.0)
        assert prob[:, [BODY_NAMES.index(b) for b in PARTS["back"]]].max() == 0.0  # upright enough


def test_reclined_sitter_leans_on_a_backrest():
    prob = kinematic_contacts(_crouch(-25.0)).prob  # trunk 25° behind vertical
    assert prob[:, [BODY_NAMES.index(b) for b in PARTS["back"]]].min() > 0.5
    assert prob[:, BODY_NAMES.index("Pelvis")].min() > 0.5
    # Completed on a bare floor: a level seat under the thighs and a backrest behind the trunk,
    # reclined like it and facing the sitter (who faces +x).
    motion = _crouch(-25.0, frames=40)
    geo = body_geometry(motion)
    contacts = filter_contacts(kinematic_contacts(motion, geometry=geo), motion, geometry=geo)
    result = complete_support(contacts, [floor_box()])
    parts = {tuple(r.bodies): b for r, b in zip(result.records, result.boxes)}
    assert set(parts) == {tuple(sorted(PARTS["seat"])), tuple(sorted(PARTS["back"]))}
    seat, back = parts[tuple(sorted(PARTS["seat"]))], parts[tuple(sorted(PARTS["back"]))]
    assert seat.rotation[2, 2] == pytest.approx(1.0)
    thigh = geo.patches[BODY_NAMES.index("L_Hip")][0, :, 2]
    assert thigh.min() - 0.01 <= seat.top_height() <= thigh.max()
    normal = back.rotation[:, 2]
    assert np.degrees(np.arctan2(normal[2], normal[0])) == pytest.approx(25.0, abs=3.0)
    assert back.center[0] < geo.body_pos[0, BODY_NAMES.index("Pelvis"), 0]


def _lean(deg: float, reach: bool, frames: int = 30) -> Motion:
    """Standing straight but tilted ``deg`` forward about flat feet; arms reaching forward or hanging."""
    dof = np.zeros((frames, len(DOF_NAMES)))
    for side in "LR":
        dof[:, DOF_NAMES.index(f"{side}_Ankle_y")] = np.radians(-deg)
    if reach:
        dof[:, DOF_NAMES.index("L_Shoulder_z")], dof[:, DOF_NAMES.index("R_Shoulder_z")] = -np.pi / 2, np.pi / 2
    else:
        dof[:, DOF_NAMES.index("L_Shoulder_x")], dof[:, DOF_NAMES.index("R_Shoulder_x")] = -1.2, 1.2
    quat = Rotation.from_euler("y", deg, degrees=True).as_quat(scalar_first=True)
    motion = Motion(fps=30.0, root_pos=np.tile([0.0, 0.0, 1.0], (frames, 1)), root_quat=np.tile(quat, (frames, 1)),
                    dof_pos=dof)
    return ground(motion, build_humanoid())


@pytest.mark.parametrize(("deg", "reach", "braced"), [(20.0, True, True), (20.0, False, False), (0.0, True, False)])
def test_hands_brace_a_body_its_feet_cannot_hold(deg, reach, braced):
    """Tilted past the toes, outstretched hands below the shoulders are the missing support;
    hanging hands are not, and an upright body needs none."""
    hands = [BODY_NAMES.index(b) for b in PARTS["hand"]]
    prob = kinematic_contacts(_lean(deg, reach)).prob
    assert (prob[:, hands].min() > 0.5) if braced else (prob[:, hands].max() == 0.0)
    assert prob[:, BODY_NAMES.index("Pelvis")].max() == 0.0


# --------------------------------------------------------------------------- completion


def _footprint_coverage(truth_xy: np.ndarray, radius: float, box: Box, spacing: float = 0.005) -> float:
    """Share of the truth's footprint (xy hull of ``truth_xy`` dilated by ``radius``) under ``box``."""
    hull = truth_xy[ConvexHull(truth_xy).vertices]
    lo, hi = hull.min(axis=0) - radius, hull.max(axis=0) + radius
    grid = np.stack(np.meshgrid(*[np.arange(a, b, spacing) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 2)
    edges = np.roll(hull, -1, axis=0) - hull
    rel = grid[:, None, :] - hull[None]
    s = np.clip(np.einsum("pei,ei->pe", rel, edges) / np.einsum("ei,ei->e", edges, edges), 0, 1)
    dist = np.linalg.norm(rel - s[..., None] * edges, axis=2).min(axis=1)
    cross = edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0]
    inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)
    footprint = grid[inside | (dist <= radius)]
    local = np.c_[footprint - box.center[:2], np.zeros(len(footprint))] @ box.rotation
    return float(np.mean(np.all(np.abs(local[:, :2]) <= box.half_size[:2], axis=1)))


def _seat_case(boxes: list[Box], motion: Motion):
    """Truth about the seat: its top, and its contact footprint: the xy hull of the seat bodies
    (pelvis and hip joints) over the ground-truth seated frames, dilated by the thigh's radius
    (half the thigh's width, 0.036 x stature)."""
    model = build_humanoid()
    seat = next(b for b in boxes if b.name == "seat")
    seated = motion.contacts[:, BODY_NAMES.index("Pelvis")]
    pos = compute_kinematics(motion, model).body_pos[seated][:, [BODY_NAMES.index(b) for b in PARTS["seat"]]]
    radius = model.geom_size[next(g for g in range(model.ngeom) if model.geom_bodyid[g] == model.body("L_Hip").id)][0]
    return seat, pos[..., :2].reshape(-1, 2), radius


@pytest.mark.parametrize("case", ["bundled", *range(10)])
def test_hidden_seat_is_completed(case):
    boxes, motion = _bundled("chair_sit") if case == "bundled" else _made("chair_sit", case)
    _, contacts = _kinematic(motion)
    assert complete_support(contacts, boxes).boxes == []  # the complete scene needs nothing
    seat, truth_xy, radius = _seat_case(boxes, motion)
    result = complete_support(contacts, [b for b in boxes if b.name != "seat"])
    assert len(result.boxes) == 1
    box = result.boxes[0]
    assert box.source == "contact" and 2 * box.half_size[2] >= 0.05
    assert abs(box.top_height() - seat.top_height()) <= SURFACE_TOLERANCE
    assert _footprint_coverage(truth_xy, radius, box) >= 0.8
    record = result.meta()[0]
    assert record["name"] == box.name and record["bodies"] == sorted(PARTS["seat"])
    assert all(motion.contacts[f, BODY_NAMES.index("Pelvis")] for f in record["frames"])
    # Reproducible.
    again = complete_support(contacts, [b for b in boxes if b.name != "seat"])
    np.testing.assert_array_equal(again.boxes[0].center, box.center)


@pytest.mark.parametrize(("kind", "seed"), [(k, s) for k in ("platform_step", "stairs_up", "stairs_down")
                                            for s in range(3)])
def test_hidden_treads_and_platforms_are_completed(kind, seed):
    boxes, motion = _made(kind, seed)
    _, contacts = _kinematic(motion)
    assert complete_support(contacts, boxes).boxes == []
    hidden = [b for b in boxes if _is_support(b)]
    result = complete_support(contacts, [b for b in boxes if not _is_support(b)])
    # Every new box lies on a hidden surface, at its height ...
    for box in result.boxes:
        tops = support_tops(box.center[None, :2], hidden)[0]
        assert np.nanmin(np.abs(tops - box.top_height())) <= SURFACE_TOLERANCE, box
    # ... and every hidden surface a foot rested on is back.
    model = build_humanoid()
    geo = body_geometry(motion, model)
    feet = [BODY_NAMES.index(b) for b in PARTS["foot"]]
    stood = {i for b in feet for p in geo.centroid(b)[motion.contacts[:, b]]
             for i, top in enumerate(support_tops(p[None, :2], hidden)[0]) if abs(top - p[2]) < 0.01}
    got = {i for box in result.boxes for i, top in enumerate(support_tops(box.center[None, :2], hidden)[0])
           if abs(top - box.top_height()) <= SURFACE_TOLERANCE}
    assert stood and stood <= got


def test_seat_is_hinged_to_its_backrest():
    boxes, motion = _made("chair_sit", 3)
    back = next(b for b in boxes if b.name == "backrest")
    seat = next(b for b in boxes if b.name == "seat")
    _, contacts = _kinematic(motion)

    def rear_and_front(box: Box) -> tuple[float, float]:
        extent = abs(box.rotation[0] @ box.half_size)  # levelled box: x extent
        return box.center[0] - extent, box.center[0] + extent

    # The sitter perches on the seat's front: the contact patch alone ends well before the back.
    alone = complete_support(contacts, [boxes[0]]).boxes[0]
    rear_alone, front = rear_and_front(alone)
    assert seat.center[0] + seat.half_size[0] <= front + 0.06
    # A backrest within hinge_distance behind that patch is met; one beyond it is left alone.
    config = CompletionConfig()
    for gap, hinged in ((0.6 * config.hinge_distance, True), (config.hinge_distance + 0.1, False)):
        moved = Box(center=back.center + [rear_alone - gap - back.half_size[0] - back.center[0], 0.0, 0.0],
                    half_size=back.half_size, name="backrest")
        rear, _ = rear_and_front(complete_support(contacts, [boxes[0], moved]).boxes[0])
        front_of_back = moved.center[0] + moved.half_size[0]
        assert rear == pytest.approx(front_of_back if hinged else rear_alone, abs=1e-6), gap


# --------------------------------------------------------------------------- imminent contacts


def _hover_case(height_range=(0.05, 0.10)):
    """platform_step with the right foot frozen 5-10 cm over the platform before it lands."""
    boxes, motion = _bundled("platform_step")
    platform = next(b for b in boxes if b.name == "platform")
    geo = body_geometry(motion)
    ankle = BODY_NAMES.index("R_Ankle")
    z = geo.centroid(ankle)[:, 2] - platform.top_height()
    landing = int(np.flatnonzero(motion.contacts[:, ankle] & (np.abs(z) < 0.01))[0])
    over = support_tops(geo.centroid(ankle)[:, :2], [platform])[:, 0] > 0
    candidates = [f for f in range(landing) if over[f] and height_range[0] <= z[f] <= height_range[1]]
    frame = candidates[-1]
    hold = 15  # 0.5 s: longer than any part's L
    return boxes, platform, _hold(motion, frame, hold), range(frame, frame + hold + 1), z[frame]


def test_hovering_foot_is_not_a_contact():
    boxes, platform, motion, hover, lift = _hover_case()
    assert 0.05 <= lift <= 0.10
    geo, contacts = _kinematic(motion)
    right = [BODY_NAMES.index(b) for b in ("R_Ankle", "R_Toe")]
    labels = contact_labels(contacts, motion.num_frames)
    assert not labels[list(hover)][:, right].any()
    # The kinematic source alone already rejects it: the sole is not at its lowest nearby.
    evidence = kinematic_contacts(motion, geometry=geo)
    alone = filter_contacts(evidence, motion, FilterConfig(suppress_radius=0.0), geometry=geo)
    assert not contact_labels(alone, motion.num_frames)[list(hover)][:, right].any()
    result = complete_support(contacts, [b for b in boxes if b.name != "platform"])
    assert len(result.boxes) == 1
    assert abs(result.boxes[0].top_height() - platform.top_height()) <= 0.01

    # A detector that over-predicts the approach (the paper's near-contact false positives):
    # the hover is still and confident, so only the suppression of a window above a lower
    # landing of the same foot rejects it.
    prob = motion.contacts.astype(float)
    prob[np.ix_(list(hover), right)] = 1.0
    evidence = ContactEvidence(prob=prob, source="external")
    kept = filter_contacts(evidence, motion, geometry=geo)
    assert not contact_labels(kept, motion.num_frames)[list(hover)][:, right].any()
    tops = [b.top_height() for b in complete_support(kept, [b for b in boxes if b.name != "platform"]).boxes]
    assert tops and all(abs(t - platform.top_height()) <= 0.01 for t in tops)
    # Without that suppression the hover does come through: the case has teeth.
    naive = filter_contacts(evidence, motion, FilterConfig(suppress_radius=0.0), geometry=geo)
    assert contact_labels(naive, motion.num_frames)[list(hover)][:, right].any()


def test_pelvis_passing_at_standing_height_is_not_a_seat():
    boxes, motion = _bundled("flat_walk")
    motion = _hold(motion, motion.num_frames // 2, 30)  # stand still mid-walk for a second
    geo, contacts = _kinematic(motion)
    assert not any(c.part == "seat" for c in contacts)
    assert complete_support(contacts, boxes).boxes == []
    # A detector claiming the pelvis sits while it walks past: the pelvis moves too fast.
    prob = motion.contacts.astype(float)
    seat = [BODY_NAMES.index(b) for b in PARTS["seat"]]
    moving = geo.speed[:, 0] > 0.5
    assert moving.sum() > motion.num_frames / 2
    prob[np.ix_(moving, seat)] = 1.0
    kept = filter_contacts(ContactEvidence(prob=prob, source="external"), motion, geometry=geo)
    assert not any(c.part == "seat" for c in kept)
    assert complete_support(kept, boxes).boxes == []


# --------------------------------------------------------------------------- external sources


def test_contacts_npz_round_trip(tmp_path):
    boxes, motion = _bundled("platform_step")
    geo, contacts = _kinematic(motion)
    path = save_contacts(contacts, tmp_path / "contacts.npz")
    evidence = load_external_contacts(path, motion)
    assert evidence.source == "points" and len(evidence.points) > 0
    again = filter_contacts(evidence, motion, geometry=geo)
    key = lambda c: (c.body, c.start, c.stop, c.frame)  # noqa: E731
    assert sorted(map(key, again)) == sorted(map(key, contacts))
    for a, b in zip(sorted(again, key=key), sorted(contacts, key=key)):
        np.testing.assert_allclose(a.points, b.points)
    hidden = [b for b in boxes if b.name != "platform"]
    assert [x.to_json() for x in complete_support(again, hidden).boxes] == \
        [x.to_json() for x in complete_support(contacts, hidden).boxes]


def test_noisy_external_contacts_make_no_spurious_surface(tmp_path):
    """Ground-truth contacts with jittered points, diluted confidences and random false positives."""
    boxes, motion = _bundled("platform_step")
    platform = next(b for b in boxes if b.name == "platform")
    geo = body_geometry(motion)
    rng = np.random.default_rng(0)
    frames, bodies = np.nonzero(motion.contacts)
    rows = [(f, BODY_NAMES[b], p + rng.normal(0, 0.01, 3), rng.uniform(0.6, 1.0))
            for f, b in zip(frames, bodies) for p in geo.patches[b][f]]
    for _ in range(400):  # confident contacts of random bodies at random places and times
        rows.append((int(rng.integers(motion.num_frames)), BODY_NAMES[rng.integers(len(BODY_NAMES))],
                     rng.uniform([-1, -1, 0], [4, 1, 1.5]), rng.uniform(0.5, 1.0)))
    path = tmp_path / "contacts.npz"
    np.savez(path, frame=np.array([r[0] for r in rows]), body=np.array([r[1] for r in rows]),
             point=np.array([r[2] for r in rows]), prob=np.array([r[3] for r in rows]))
    contacts = filter_contacts(load_external_contacts(path, motion), motion, geometry=geo)
    assert complete_support(contacts, boxes).boxes == []
    result = complete_support(contacts, [b for b in boxes if b.name != "platform"])
    assert len(result.boxes) == 1
    assert abs(result.boxes[0].top_height() - platform.top_height()) <= SURFACE_TOLERANCE
    assert set(result.records[0].bodies) <= set(PARTS["foot"])


@pytest.mark.parametrize("layout", ["smpl_indices", "names_in_file", "npy"])
def test_per_vertex_probabilities(tmp_path, layout):
    _, motion = _bundled("chair_sit")
    rng = np.random.default_rng(1)
    smpl_index = rng.integers(len(SMPL_JOINT_NAMES), size=NUM_SMPL_VERTICES)
    owner = np.array([BODY_NAMES.index(SMPL_TO_BODY[SMPL_JOINT_NAMES[i]]) for i in smpl_index])
    scores = np.full((motion.num_frames, NUM_SMPL_VERTICES), 0.05)
    for b in range(len(BODY_NAMES)):
        verts = np.flatnonzero(owner == b)
        touching = verts[: max(1, int(0.3 * len(verts)))]  # the part of the body that touches
        scores[np.ix_(np.flatnonzero(motion.contacts[:, b]), touching)] = 0.9
    lone = rng.integers(NUM_SMPL_VERTICES, size=motion.num_frames)
    scores[np.arange(motion.num_frames), lone] = 1.0  # one confident vertex per frame is noise
    if layout == "smpl_indices":
        np.savez(tmp_path / "ivlm.npz", pred_contact_3d_smplh=scores)
        np.savez(tmp_path / "map.npz", vertex_body=smpl_index)
        evidence = load_external_contacts(tmp_path / "ivlm.npz", motion, vertex_map=tmp_path / "map.npz")
    elif layout == "names_in_file":
        np.savez(tmp_path / "ivlm.npz", pred_contact_3d_smplh=scores, vertex_body=np.array(BODY_NAMES)[owner])
        evidence = load_external_contacts(tmp_path / "ivlm.npz", motion)
    else:
        np.save(tmp_path / "ivlm.npy", scores)
        np.savez(tmp_path / "map.npz", vertex_body=np.array(SMPL_JOINT_NAMES)[smpl_index])
        evidence = load_external_contacts(tmp_path / "ivlm.npy", motion, vertex_map=tmp_path / "map.npz")
    assert evidence.source == "vertices"
    np.testing.assert_array_equal(evidence.prob >= 0.5, motion.contacts)


def test_bad_contact_files_are_clear_errors(tmp_path):
    _, motion = _bundled("flat_walk")
    with pytest.raises(FileNotFoundError, match="no contact file"):
        load_external_contacts(tmp_path / "missing.npz", motion)
    np.savez(tmp_path / "other.npz", foo=np.zeros(3))
    with pytest.raises(ValueError, match="neither a contacts.npz"):
        load_external_contacts(tmp_path / "other.npz", motion)
    good = dict(frame=np.array([0, 1]), body=np.array(["L_Ankle", "Head"]), point=np.zeros((2, 3)),
                prob=np.array([0.9, 0.8]))
    for change, message in ((dict(body=np.array(["L_Ankle", "Tail"])), "unknown body 'Tail'"),
                            (dict(frame=np.array([0, motion.num_frames])), "frames must lie in"),
                            (dict(point=np.zeros((2, 2))), "point \\(M, 3\\)"),
                            (dict(prob=np.array([0.5, 1.5])), "prob within")):
        np.savez(tmp_path / "bad.npz", **{**good, **change})
        with pytest.raises(ValueError, match=message):
            load_external_contacts(tmp_path / "bad.npz", motion)
    np.savez(tmp_path / "ivlm.npz", pred_contact_3d_smplh=np.zeros((motion.num_frames, NUM_SMPL_VERTICES)))
    with pytest.raises(ValueError, match="pass vertex_map"):
        load_external_contacts(tmp_path / "ivlm.npz", motion)
    np.savez(tmp_path / "map.npz", vertex_body=np.zeros(100, dtype=int))
    with pytest.raises(ValueError, match="6890 entries"):
        load_external_contacts(tmp_path / "ivlm.npz", motion, vertex_map=tmp_path / "map.npz")
    np.savez(tmp_path / "short.npz", pred_contact_3d_smplh=np.zeros((3, NUM_SMPL_VERTICES)))
    with pytest.raises(ValueError, match="must be \\(T="):
        load_external_contacts(tmp_path / "short.npz", motion)
    with pytest.raises(ValueError, match="prob must have shape"):
        ContactEvidence(prob=np.zeros((5, 3)), source="test")
    with pytest.raises(ValueError, match="must cover the motion"):
        filter_contacts(ContactEvidence(prob=np.zeros((5, 24)), source="test"), motion)
    with pytest.raises(ValueError, match="at least 0.05 m"):
        CompletionConfig(thickness=0.01)


def test_floor_the_camera_missed_is_built_under_the_feet():
    """The scene is only its boxes: when the seen floor is a far patch, the pipeline's completion
    builds floor under the walking feet (the humanoid would fall through z = 0 otherwise)."""
    from crisp_gym.reconstruct.contact import ContactConfig, contact_completion

    clip = load_clip("flat_walk")
    far_patch = Box(center=[clip.motion.root_pos[:, 0].max() + 3.0, 0.0, -0.025], half_size=[0.3, 0.3, 0.025])
    result = contact_completion(clip.motion, [far_patch], "kinematic", ContactConfig())
    assert result.boxes, "the feet's floor must come back"
    for box in result.boxes:
        assert abs(box.top_height()) < 0.03, box
    # a floor that covers the walk needs nothing new
    assert contact_completion(clip.motion, [floor_box()], "kinematic", ContactConfig()).boxes == []
    # under the stance feet, the completed scene has a top at floor height
    geo = body_geometry(clip.motion, build_humanoid())
    feet = [BODY_NAMES.index(b) for b in PARTS["foot"]]
    stance = np.concatenate([geo.centroid(b)[clip.motion.contacts[:, b]] for b in feet])
    tops = support_tops(stance[:, :2], result.boxes + [far_patch])
    assert np.mean(np.nanmin(np.abs(tops), axis=1) < 0.03) > 0.9


@pytest.mark.parametrize("toe_raised", [False, True])
def test_heel_raised_over_its_standing_toe_needs_no_support(toe_raised):
    """A seated foot on its toes (the real phone video's sitter): the heel is still and low
    nearby, so it reads as a contact, but its own toe stands on the floor and bears the foot.
    No box may be built under the heel (the toe would stand 6 cm inside it). The same heel
    with its toe raised too is a whole foot on an unseen step: that support is built."""
    from dataclasses import replace

    boxes, motion = _bundled("chair_sit")
    geo = body_geometry(motion)
    seated = np.flatnonzero(motion.contacts[:, BODY_NAMES.index("Pelvis")])
    lift = np.zeros((motion.num_frames, 1, 3))
    lift[seated, :, 2] = 0.06
    raised = {"R_Ankle"} | ({"R_Toe"} if toe_raised else set())
    patches = tuple(p + lift if BODY_NAMES[i] in raised else p for i, p in enumerate(geo.patches))
    geo = replace(geo, patches=patches)
    heel = patches[BODY_NAMES.index("R_Ankle")]
    half = len(seated) // 2
    contacts = [Contact(body="R_Ankle", part="foot", frame=int(w[len(w) // 2]), start=int(w[0]), stop=int(w[-1]) + 1,
                        prob=1.0, points=heel[w[len(w) // 2]], normal=np.array([0.0, 0.0, 1.0]))
                for w in (seated[:half], seated[half:])]
    built = complete_support(contacts, boxes, CompletionConfig(floor_height=None))
    assert len(built.boxes) == 1 and abs(built.boxes[0].top_height() - 0.06) < 0.02  # without the foot's geometry
    with_foot = complete_support(contacts, boxes, CompletionConfig(floor_height=None), geometry=geo)
    assert len(with_foot.boxes) == (1 if toe_raised else 0)
