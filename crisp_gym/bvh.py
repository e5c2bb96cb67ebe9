"""BVH motion capture files: parsing, forward kinematics and retargeting onto the humanoid.

A BVH file has a HIERARCHY (joints with a rest OFFSET from their parent, CHANNELS, and
optional End Sites) and a MOTION section (one row of channel values per frame). Rotation
channels compose in the order written (``Zrotation Xrotation Yrotation`` means
``Rz @ Rx @ Ry``, intrinsic); position channels give the joint's translation in its
parent's frame in place of its OFFSET. In the rest pose (all rotations zero) every joint
frame is parallel to the file's world frame.

Retargeting maps BVH joints to our 24 bodies by name (:data:`JOINT_MAPS`) and aligns rest
poses: our humanoid rests in a T-pose, a BVH may rest with arms down or legs apart, so each
of our bodies takes the world rotation of its BVH joint *relative to the BVH rest*, composed
with the fixed rotation that turns our rest bone into the BVH's rest bone (a foot only to the
BVH foot's heading: both rest poses stand on flat feet). The file's axes
(up from ``up_axis``, facing from the rest hips) become ours: z up, facing +x, left +y.
The root follows the file's root joint; only its height is then corrected, by a smooth
per-frame offset that puts the planted feet on the floor (captured floors drift by a few
centimetres within a take, and one constant offset leaves feet floating or sunk). Before
that, planted feet are laid flat (:func:`~crisp_gym.motion.level_feet`): their soles are
turned level across and the toes are posed from the floor, not from the file. Captured feet
are often rolled onto an edge (CMU's by 10-20°) and captured toes curl into the floor and flip
by 80° within a few frames; both lifted the body onto the edge or the toe tips, and the
simulated toes, fighting the floor, chattered at hundreds of rad/s. The hinge angles
of the forearms and hands are low-passed at 6 Hz first (:func:`~crisp_gym.motion.low_pass_joints`):
captured hands flicker (CMU 131_01's right wrist turns at up to 6,500 °/s relative to the forearm).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from crisp_gym.humanoid import BODY_NAMES, PARENTS, default_rest_joints
from crisp_gym.motion import Motion, StanceGrounding
from crisp_gym.retarget import motion_from_rotations

_AXES = {"X": 0, "Y": 1, "Z": 2}
_ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")
_POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")


@dataclass(frozen=True)
class BvhSkeleton:
    """The HIERARCHY of a BVH file, joints in file (depth-first) order.

    Attributes:
        names: joint names.
        parents: (J,) parent index, -1 for the root.
        offsets: (J, 3) rest offset of each joint from its parent, file units and axes.
        channels: each joint's channel names, in file order.
        end_sites: joint index -> (3,) End Site offset, for joints that end a chain.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_sites: dict[int, np.ndarray]

    @property
    def num_channels(self) -> int:
        return sum(len(c) for c in self.channels)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def rest_positions(self) -> np.ndarray:
        """(J, 3) joint positions in the rest pose (root at the origin plus its offset)."""
        pos = np.zeros((len(self.names), 3))
        for j, p in enumerate(self.parents):
            pos[j] = self.offsets[j] + (pos[p] if p >= 0 else 0.0)
        return pos


@dataclass(frozen=True)
class BvhClip:
    """A parsed BVH file.

    Attributes:
        skeleton: the hierarchy.
        frame_time: seconds per frame.
        local_rotations: (T, J, 3, 3) rotation of each joint in its parent's frame.
        local_translations: (T, J, 3) translation of each joint in its parent's frame (the
            OFFSET, replaced axis by axis by position channels where the joint has them).
    """

    skeleton: BvhSkeleton
    frame_time: float
    local_rotations: np.ndarray
    local_translations: np.ndarray

    @property
    def num_frames(self) -> int:
        return self.local_rotations.shape[0]

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    @property
    def root_positions(self) -> np.ndarray:
        """(T, 3) root joint positions, file units and axes."""
        return self.local_translations[:, 0]


def bvh_forward_kinematics(clip: BvhClip) -> tuple[np.ndarray, np.ndarray]:
    """World joint positions (T, J, 3) and rotations (T, J, 3, 3), file units and axes."""
    parents = clip.skeleton.parents
    t, j = clip.local_rotations.shape[:2]
    pos = np.empty((t, j, 3))
    rot = np.empty((t, j, 3, 3))
    for k, p in enumerate(parents):
        if p < 0:
            pos[:, k] = clip.local_translations[:, k]
            rot[:, k] = clip.local_rotations[:, k]
        else:
            pos[:, k] = pos[:, p] + np.einsum("tab,tb->ta", rot[:, p], clip.local_translations[:, k])
            rot[:, k] = rot[:, p] @ clip.local_rotations[:, k]
    return pos, rot


# --- parsing -------------------------------------------------------------------------------


def _floats(tokens: list[str], what: str) -> np.ndarray:
    try:
        return np.array([float(x) for x in tokens])
    except ValueError:
        raise ValueError(f"{what}: expected numbers, got {' '.join(tokens)!r}") from None


def _parse_hierarchy(tokens: list[str], source: str) -> BvhSkeleton:
    """Read joints from the tokens between HIERARCHY and MOTION."""
    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []
    channels: list[tuple[str, ...]] = []
    end_sites: dict[int, np.ndarray] = {}
    stack: list[int] = []  # open joints; -2 marks an open End Site
    i = 0

    def take(n: int) -> list[str]:
        nonlocal i
        if i + n > len(tokens):
            raise ValueError(f"{source}: HIERARCHY ends early (expected {n} more tokens after "
                             f"{' '.join(tokens[max(0, i - 3):i])!r})")
        out = tokens[i:i + n]
        i += n
        return out

    while i < len(tokens):
        word = take(1)[0]
        if word in ("ROOT", "JOINT"):
            if (word == "ROOT") != (not stack):
                raise ValueError(f"{source}: {word} at the wrong level (one ROOT, JOINTs inside it)")
            name, brace = take(2)
            if brace != "{":
                raise ValueError(f"{source}: expected '{{' after {word} {name}, got {brace!r}")
            if name in names:
                raise ValueError(f"{source}: joint name {name!r} appears twice")
            parents.append(stack[-1] if stack else -1)
            names.append(name)
            offsets.append(np.zeros(3))
            channels.append(())
            stack.append(len(names) - 1)
        elif word == "End":
            site, brace = take(2)
            if site != "Site" or brace != "{" or not stack or stack[-1] < 0:
                raise ValueError(f"{source}: malformed End Site (expected 'End Site {{' inside a joint)")
            stack.append(-2)
        elif word == "OFFSET":
            if not stack:
                raise ValueError(f"{source}: OFFSET outside a joint")
            value = _floats(take(3), f"{source}: OFFSET")
            if stack[-1] == -2:
                end_sites.setdefault(stack[-2], value)
            else:
                offsets[stack[-1]] = value
        elif word == "CHANNELS":
            if not stack or stack[-1] < 0:
                raise ValueError(f"{source}: CHANNELS outside a joint")
            try:
                n = int(take(1)[0])
            except ValueError:
                raise ValueError(f"{source}: CHANNELS of {names[stack[-1]]} must start with a count") from None
            chans = tuple(take(n))
            allowed = _ROTATION_CHANNELS + _POSITION_CHANNELS
            bad = [c for c in chans if c not in allowed]
            if bad or len(set(chans)) != n:
                raise ValueError(f"{source}: joint {names[stack[-1]]} has CHANNELS {' '.join(chans)}; "
                                 f"expected {n} distinct names from {' '.join(allowed)}")
            channels[stack[-1]] = chans
        elif word == "}":
            if not stack:
                raise ValueError(f"{source}: unbalanced '}}' in HIERARCHY")
            stack.pop()
        else:
            raise ValueError(f"{source}: unexpected {word!r} in HIERARCHY (expected ROOT, JOINT, "
                             "End Site, OFFSET, CHANNELS or braces)")
    if stack:
        raise ValueError(f"{source}: HIERARCHY has {len(stack)} unclosed '{{'")
    if not names:
        raise ValueError(f"{source}: HIERARCHY has no ROOT joint")
    return BvhSkeleton(tuple(names), np.array(parents), np.array(offsets), tuple(channels), end_sites)


def _header_value(line: str, key: str, source: str) -> float:
    head, _, value = line.partition(":")
    if head.strip().lower() != key.lower():
        raise ValueError(f"{source}: expected '{key}: <number>' in MOTION, got {line.strip()!r}")
    try:
        return float(value)
    except ValueError:
        raise ValueError(f"{source}: '{key}:' must be followed by a number, got {value.strip()!r}") from None


def _channel_arrays(skeleton: BvhSkeleton, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations and translations from (T, C) channel values."""
    t = values.shape[0]
    j = len(skeleton.names)
    rotations = np.broadcast_to(np.eye(3), (t, j, 3, 3)).copy()
    translations = np.broadcast_to(skeleton.offsets, (t, j, 3)).copy()
    column = 0
    for k, chans in enumerate(skeleton.channels):
        cols = {c: column + n for n, c in enumerate(chans)}
        column += len(chans)
        for axis, c in enumerate(_POSITION_CHANNELS):
            if c in cols:
                translations[:, k, axis] = values[:, cols[c]]
        order = [c for c in chans if c in _ROTATION_CHANNELS]
        if order:
            seq = "".join(c[0] for c in order)  # uppercase: intrinsic, composed as written
            angles = values[:, [cols[c] for c in order]]
            rotations[:, k] = Rotation.from_euler(seq, angles, degrees=True).as_matrix()
    return rotations, translations


def parse_bvh(path: str | Path) -> BvhClip:
    """Read a BVH file; raises ``ValueError`` naming what is malformed."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no BVH file at {path}")
    source = str(path)
    lines = path.read_text(errors="replace").splitlines()
    starts = [n for n, line in enumerate(lines) if line.strip()]
    if not starts or lines[starts[0]].strip() != "HIERARCHY":
        raise ValueError(f"{source}: not a BVH file (expected 'HIERARCHY' on the first line)")
    motion_at = next((n for n, line in enumerate(lines) if line.strip() == "MOTION"), None)
    if motion_at is None:
        raise ValueError(f"{source}: no MOTION section (expected 'MOTION' after the HIERARCHY)")
    text = " ".join(lines[starts[0] + 1:motion_at]).replace("{", " { ").replace("}", " } ")
    skeleton = _parse_hierarchy(text.split(), source)

    body = [(n, line) for n, line in enumerate(lines[motion_at + 1:], start=motion_at + 2) if line.strip()]
    if len(body) < 2:
        raise ValueError(f"{source}: MOTION section is truncated (expected 'Frames:' and 'Frame Time:')")
    frames = _header_value(body[0][1], "Frames", source)
    frame_time = _header_value(body[1][1], "Frame Time", source)
    if frames != int(frames) or frames < 1:
        raise ValueError(f"{source}: 'Frames:' must be a positive integer, got {frames}")
    if not np.isfinite(frame_time) or frame_time <= 0:
        raise ValueError(f"{source}: 'Frame Time:' must be a positive number of seconds, got {frame_time}")
    rows = body[2:]
    if len(rows) != int(frames):
        raise ValueError(f"{source}: MOTION declares {int(frames)} frames but has {len(rows)} rows "
                         "(truncated or extra lines)")
    n_chan = skeleton.num_channels
    values = np.empty((len(rows), n_chan))
    for k, (line_no, line) in enumerate(rows):
        tokens = line.split()
        if len(tokens) != n_chan:
            raise ValueError(f"{source}: line {line_no} (frame {k}) has {len(tokens)} values; the "
                             f"HIERARCHY declares {n_chan} channels")
        values[k] = _floats(tokens, f"{source}: line {line_no}")
    if not np.all(np.isfinite(values)):
        frame = int(np.argwhere(~np.isfinite(values))[0, 0])
        raise ValueError(f"{source}: non-finite channel value in frame {frame}")
    rotations, translations = _channel_arrays(skeleton, values)
    return BvhClip(skeleton, float(frame_time), rotations, translations)


# --- retargeting ---------------------------------------------------------------------------


def _sided(left: Mapping[str, str]) -> dict[str, str]:
    """A body -> joint table for both sides from its left half ("{Side}" -> Left/Right, "{s}" -> l/r)."""
    out: dict[str, str] = {}
    for body, joint in left.items():
        if body.startswith("L_"):
            out[body] = joint.format(Side="Left", s="l")
            out["R_" + body[2:]] = joint.format(Side="Right", s="r")
        else:
            out[body] = joint
    return out


JOINT_MAPS: dict[str, dict[str, str]] = {
    # CMU mocap as converted to BVH by cgspeed (31 joints).
    "cmu_cgspeed": _sided({
        "Pelvis": "Hips", "L_Hip": "{Side}UpLeg", "L_Knee": "{Side}Leg", "L_Ankle": "{Side}Foot",
        "L_Toe": "{Side}ToeBase", "Torso": "LowerBack", "Spine": "Spine", "Chest": "Spine1",
        "Neck": "Neck1", "Head": "Head", "L_Thorax": "{Side}Shoulder", "L_Shoulder": "{Side}Arm",
        "L_Elbow": "{Side}ForeArm", "L_Wrist": "{Side}Hand", "L_Hand": "{Side}FingerBase",
    }),
    # CMU mocap with the ASF/AMC-style names (LeftHip is the thigh, LeftShoulder the upper arm).
    "cmu_amc": _sided({
        "Pelvis": "Hips", "L_Hip": "{Side}Hip", "L_Knee": "{Side}Knee", "L_Ankle": "{Side}Ankle",
        "L_Toe": "{Side}Toe", "Torso": "lowerback", "Spine": "Chest", "Chest": "Chest2",
        "Neck": "Neck", "Head": "Head", "L_Thorax": "{Side}Collar", "L_Shoulder": "{Side}Shoulder",
        "L_Elbow": "{Side}Elbow", "L_Wrist": "{Side}Wrist", "L_Hand": "{s}hand",
    }),
    # Mixamo (a "mixamorig:" style namespace prefix is ignored).
    "mixamo": _sided({
        "Pelvis": "Hips", "L_Hip": "{Side}UpLeg", "L_Knee": "{Side}Leg", "L_Ankle": "{Side}Foot",
        "L_Toe": "{Side}ToeBase", "Torso": "Spine", "Spine": "Spine1", "Chest": "Spine2",
        "Neck": "Neck", "Head": "Head", "L_Thorax": "{Side}Shoulder", "L_Shoulder": "{Side}Arm",
        "L_Elbow": "{Side}ForeArm", "L_Wrist": "{Side}Hand", "L_Hand": "{Side}HandMiddle1",
    }),
}  # fmt: skip
"""Our body -> BVH joint name, per naming convention; the best-matching table is used."""

REQUIRED_BODIES: tuple[str, ...] = (
    "Pelvis", "L_Hip", "L_Knee", "L_Ankle", "R_Hip", "R_Knee", "R_Ankle",
    "L_Shoulder", "L_Elbow", "R_Shoulder", "R_Elbow",
)  # fmt: skip
"""Bodies a BVH must provide; the others keep their parent's orientation when missing."""

# Our rest bone direction for bodies that end a chain (their geoms point this way).
_END_DIRECTIONS = {"L_Toe": (1.0, 0.0, 0.0), "R_Toe": (1.0, 0.0, 0.0), "Head": (0.0, 0.0, 1.0),
                   "L_Hand": (0.0, 1.0, 0.0), "R_Hand": (0.0, -1.0, 0.0)}
# The child whose joint gives a multi-child body its bone (the pelvis has none).
_BONE_CHILD = {"Chest": "Neck"}
# Bodies aligned by their heading alone (see rest_alignment).
_FEET = ("L_Ankle", "R_Ankle")

# Metres per file unit that BVH files use; CMU's ASF unit is 1/0.45 inch.
KNOWN_UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "inch": 0.0254, "cmu": 0.0254 / 0.45}
_LEG_PER_STATURE = 0.491  # hip-to-ankle length / stature (Drillis & Contini, as in humanoid.py)
_STATURE_RANGE = (1.2, 2.2)  # metres accepted when guessing the unit


def _base_name(name: str) -> str:
    """'mixamorig:LeftArm' -> 'leftarm' (namespace dropped, case folded)."""
    return name.rsplit(":", 1)[-1].lower()


def match_joints(skeleton: BvhSkeleton, joint_map: Mapping[str, str] | None = None) -> dict[str, int]:
    """Our body name -> BVH joint index, from ``joint_map`` or the best table in :data:`JOINT_MAPS`."""
    lookup = {_base_name(n): k for k, n in enumerate(skeleton.names)}
    if joint_map is not None:
        unknown = sorted(set(joint_map) - set(BODY_NAMES))
        if unknown:
            raise ValueError(f"joint_map keys must be our body names {BODY_NAMES}, got {unknown}")
        tables = {"joint_map": dict(joint_map)}
    else:
        tables = JOINT_MAPS
    found = {key: {b: lookup[_base_name(j)] for b, j in table.items() if _base_name(j) in lookup}
             for key, table in tables.items()}
    best = max(found, key=lambda key: len(found[key]))
    missing = [b for b in REQUIRED_BODIES if b not in found[best]]
    if missing:
        wanted = [tables[best].get(b, "?") for b in missing]
        raise ValueError(f"BVH skeleton lacks joints for {missing} (looked for {wanted} in the "
                         f"{best!r} naming); its joints are {list(skeleton.names)}; pass joint_map")
    return found[best]


def detect_unit_scale(skeleton: BvhSkeleton, mapping: Mapping[str, int]) -> float:
    """Metres per file unit: the known unit that makes the legs those of a 1.2-2.2 m person."""
    rest = skeleton.rest_positions()
    leg = np.mean([np.linalg.norm(rest[mapping[f"{s}_Hip"]] - rest[mapping[f"{s}_Knee"]])
                   + np.linalg.norm(rest[mapping[f"{s}_Knee"]] - rest[mapping[f"{s}_Ankle"]])
                   for s in "LR"])
    statures = {name: leg / _LEG_PER_STATURE * scale for name, scale in KNOWN_UNITS.items()}
    plausible = {n: s for n, s in statures.items() if _STATURE_RANGE[0] <= s <= _STATURE_RANGE[1]}
    if not plausible:
        listed = ", ".join(f"{n}: {s:.3g} m" for n, s in statures.items())
        raise ValueError(f"cannot tell the BVH's length unit: its legs are {leg:.4g} units long, which "
                         f"in the known units gives a stature of {listed}; none is a human's "
                         f"({_STATURE_RANGE[0]}-{_STATURE_RANGE[1]} m). Pass unit_scale (metres per unit).")
    name = min(plausible, key=lambda n: abs(np.log(plausible[n] / 1.7)))
    return KNOWN_UNITS[name]


def detect_up_axis(skeleton: BvhSkeleton, mapping: Mapping[str, int]) -> str:
    """The file's up axis (``x``, ``y`` or ``z``): the one its rest pose's hips-to-head line
    runs along (every BVH rests standing)."""
    rest = skeleton.rest_positions()
    rise = rest[mapping["Head"]] - (rest[mapping["L_Hip"]] + rest[mapping["R_Hip"]]) / 2
    axis = int(np.argmax(np.abs(rise)))
    if rise[axis] <= 0 or abs(rise[axis]) < 0.8 * np.linalg.norm(rise):
        raise ValueError(f"cannot tell the BVH's up axis: its rest pose runs from the hips to the head "
                         f"along {np.round(rise / np.linalg.norm(rise), 2)}, not up one of +x, +y, +z. "
                         f"Pass up_axis.")
    return "xyz"[axis]


def _file_to_ours(skeleton: BvhSkeleton, mapping: Mapping[str, int], up_axis: str) -> np.ndarray:
    """(3, 3) rotation from file axes to ours: up -> z, the rest body's facing -> x."""
    if up_axis not in ("x", "y", "z"):
        raise ValueError(f"up_axis must be 'x', 'y', 'z' or 'auto', got {up_axis!r}")
    up = np.eye(3)["xyz".index(up_axis)]
    rest = skeleton.rest_positions()
    left = rest[mapping["L_Hip"]] - rest[mapping["R_Hip"]]
    left = left - up * (left @ up)
    if np.linalg.norm(left) < 1e-9:
        raise ValueError(f"the BVH's left and right hips coincide across the up axis {up_axis!r}; "
                         "is up_axis right?")
    left /= np.linalg.norm(left)
    return np.stack([np.cross(left, up), left, up])


def _shortest_arc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation matrix turning unit vector ``a`` onto unit vector ``b`` by the smallest angle."""
    axis = np.cross(a, b)
    sin, cos = np.linalg.norm(axis), float(a @ b)
    if sin < 1e-9:
        if cos > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        sin = np.linalg.norm(axis)
    return Rotation.from_rotvec(axis / sin * np.arctan2(sin, cos)).as_matrix()


def _tip(skeleton: BvhSkeleton, rest: np.ndarray, joint: int, eps: float) -> np.ndarray | None:
    """Rest position of the first point down the first-child chain of ``joint`` away from it."""
    children = {k: [c for c, p in enumerate(skeleton.parents) if p == k] for k in range(len(rest))}
    k = joint
    while True:
        if children[k]:
            k = children[k][0]
            point = rest[k]
        elif k in skeleton.end_sites:
            point = rest[k] + skeleton.end_sites[k]
        else:
            return None
        if np.linalg.norm(point - rest[joint]) > eps:
            return point
        if not children[k]:
            return None


def rest_alignment(skeleton: BvhSkeleton, mapping: Mapping[str, int], to_ours: np.ndarray) -> dict[str, np.ndarray]:
    """Per mapped body, the rotation (our axes) taking our rest bone onto the BVH's rest bone.

    Feet are the exception: a rest pose stands on flat feet, and how steeply the ankle-to-toe
    bone descends is anatomy, not posture (ours 18°, CMU's 10-13°), so a foot is only turned to
    the BVH foot's heading; matching the bone would stand our flat foot on its heel. A rest
    foot pointing more than 60° down is not standing, and is aligned by its bone.
    """
    rest = skeleton.rest_positions()
    eps = 1e-6 * np.ptp(rest, axis=0).max()
    ours = default_rest_joints(1.0)
    children = {b: [c for c in BODY_NAMES if PARENTS[c] == b] for b in BODY_NAMES}
    align = {"Pelvis": np.eye(3)}
    for body, joint in mapping.items():
        if body == "Pelvis":
            continue
        child = _BONE_CHILD.get(body) or (children[body][0] if len(children[body]) == 1 else None)
        if child is None:
            ours_dir = np.array(_END_DIRECTIONS[body])
        else:
            ours_dir = ours[BODY_NAMES.index(child)] - ours[BODY_NAMES.index(body)]
        target = rest[mapping[child]] if child in mapping else None
        if target is None or np.linalg.norm(target - rest[joint]) <= eps:
            target = _tip(skeleton, rest, joint, eps)
        if target is None:
            align[body] = np.eye(3)  # nothing below the joint to align with
            continue
        bvh_dir = to_ours @ (target - rest[joint])
        if body in _FEET and np.linalg.norm(bvh_dir[:2]) > 0.5 * np.linalg.norm(bvh_dir):
            ours_dir, bvh_dir = ours_dir * [1.0, 1.0, 0.0], bvh_dir * [1.0, 1.0, 0.0]
        align[body] = _shortest_arc(ours_dir / np.linalg.norm(ours_dir), bvh_dir / np.linalg.norm(bvh_dir))
    return align


@dataclass(frozen=True)
class BvhRetarget:
    """The result of :func:`retarget_bvh`, with what was done to get it.

    Attributes:
        motion: the humanoid motion, grounded (planted feet flat on z = 0).
        unit_scale: metres per BVH unit used.
        joints: our body -> the BVH joint name that drives it.
        to_ours: (3, 3) rotation from the file's axes to ours.
        clipped_fraction: share of hinge values changed to fit the joints into the humanoid's ranges.
        max_clip_deg: the largest turn of a joint that fitting into range caused, in degrees.
        ground_offset: (T,) metres added to each frame's root height to put the feet on the
            floor: a slowly varying correction where the capture's floor drifts, constant
            when grounded without ``grounding``.
        up_axis: the file's up axis used (given, or detected).
    """

    motion: Motion
    unit_scale: float
    joints: dict[str, str]
    to_ours: np.ndarray
    clipped_fraction: float
    max_clip_deg: float
    ground_offset: np.ndarray
    up_axis: str


def retarget_bvh(clip: BvhClip, *, unit_scale: float | None = None, up_axis: str = "auto",
                 joint_map: Mapping[str, str] | None = None, clip_to_range: bool = True,
                 model: mujoco.MjModel | None = None,
                 grounding: StanceGrounding | None = StanceGrounding(),
                 low_pass_hz: float | None = 6.0) -> BvhRetarget:
    """Retarget a parsed BVH onto the humanoid (see the module docstring for the method).

    ``up_axis`` is the file's up axis (``x``, ``y``, ``z``; ``auto`` detects it, see
    :func:`detect_up_axis`). ``joint_map`` (our body -> BVH joint name) replaces the built-in tables; ``model`` is the
    humanoid used for grounding (the default 1.70 m one when ``None``). ``grounding`` lays the
    planted feet flat (:func:`~crisp_gym.motion.level_feet`) and puts them on the floor frame by
    frame (motion capture floors drift by centimetres over a take, see
    :func:`~crisp_gym.motion.stance_floor`); ``None`` keeps the feet as retargeted and shifts the
    whole motion by one offset instead (:func:`~crisp_gym.motion.ground`). ``clip_to_range``
    fits the joints into the humanoid's ranges after the feet are laid flat, keeping each foot where
    it was (:func:`~crisp_gym.motion.fit_into_range`). ``low_pass_hz`` low-passes the elbows', wrists'
    and hands' hinge angles first (:data:`~crisp_gym.retarget.FLICKERING_BODIES`,
    :func:`~crisp_gym.motion.low_pass_joints`; ``None``: as captured).
    """
    skeleton = clip.skeleton
    mapping = match_joints(skeleton, joint_map)
    if unit_scale is None:
        unit_scale = detect_unit_scale(skeleton, mapping)
    elif not np.isfinite(unit_scale) or unit_scale <= 0:
        raise ValueError(f"unit_scale must be a positive number of metres per BVH unit, got {unit_scale}")
    if up_axis == "auto":
        up_axis = detect_up_axis(skeleton, mapping)
    to_ours = _file_to_ours(skeleton, mapping, up_axis)
    align = rest_alignment(skeleton, mapping, to_ours)

    positions, world = bvh_forward_kinematics(clip)
    world = np.einsum("ab,tjbc,dc->tjad", to_ours, world, to_ours)
    rotations = np.empty((clip.num_frames, len(BODY_NAMES), 3, 3))
    for i, body in enumerate(BODY_NAMES):
        # An unmapped body keeps its parent's orientation (its local rotation is the identity).
        rotations[:, i] = world[:, mapping[body]] @ align[body] if body in mapping else \
            rotations[:, BODY_NAMES.index(PARENTS[body])]
    root_pos = positions[:, mapping["Pelvis"]] @ to_ours.T * unit_scale
    result = motion_from_rotations(rotations, root_pos, clip.fps, model=model, grounding=grounding,
                                   clip_to_range=clip_to_range, low_pass_hz=low_pass_hz)
    return BvhRetarget(result.motion, float(unit_scale), {b: skeleton.names[k] for b, k in mapping.items()},
                       to_ours, result.clipped_fraction, result.max_clip_deg, result.ground_offset, up_axis)


def load_bvh(path: str | Path, *, unit_scale: float | None = None, up_axis: str = "auto",
             target_fps: float | None = None) -> Motion:
    """A BVH file as a grounded humanoid :class:`Motion`, resampled to ``target_fps`` if given.

    ``unit_scale`` is metres per file unit (guessed from the leg length when ``None``);
    ``up_axis`` is the file's up axis (``auto``: detected). Use :func:`parse_bvh` and :func:`retarget_bvh` to see
    the unit, clipping and grounding that were applied.
    """
    motion = retarget_bvh(parse_bvh(path), unit_scale=unit_scale, up_axis=up_axis).motion
    return motion.resample(target_fps) if target_fps is not None else motion

