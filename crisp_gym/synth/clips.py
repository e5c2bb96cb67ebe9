"""Synthetic clips: :func:`make_clip` (scene, motion and meta of a kind and seed), the bundled set
(``assets/clips``, written by :func:`bundle_clips`) and ``crisp synth-clips``."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import tyro

from crisp_gym.bundled import BUNDLED_CLIPS, BUNDLED_REGISTRY
from crisp_gym.clip import write_clip
from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, FEET, HumanoidConfig, build_humanoid, joint_range_deg
from crisp_gym.metrics import sole_points, support_tops
from crisp_gym.motion import Motion
from crisp_gym.registry import check_clip_name, register_clip, user_clips_dir, write_registry
from crisp_gym.scene import Box, floor_box
from crisp_gym.synth.gait import (
    PELVIS_AHEAD,
    MotionPlan,
    WalkPath,
    add_walk,
    even_positions,
    footsteps,
    sample_gait,
    terrain_anchors,
)
from crisp_gym.synth.ik import plan_to_motion, sample_plan
from crisp_gym.synth.scenes import (
    Level,
    platform_boxes,
    sample_platform_params,
    sample_seat_params,
    sample_stairs_params,
    seat_boxes,
    stairs_boxes,
    stairs_levels,
)
from crisp_gym.synth.sitting import SEAT_BODIES, add_sit, seat_contacts
from crisp_gym.synth.skeleton import STANCE_BODIES, Skeleton

KINDS: tuple[str, ...] = ("flat_walk", "stairs_up", "stairs_down", "platform_step", "chair_sit")
"""Clip kinds :func:`make_clip` generates."""


BUNDLED: dict[str, tuple[str, int]] = {
    "flat_walk": ("flat_walk", 1),
    "stairs_up": ("stairs_up", 1),
    "stairs_down": ("stairs_down", 1),
    "platform_step": ("platform_step", 1),
    "chair_sit": ("chair_sit", 1),
}
"""Bundled clip name -> (kind, seed)."""


TAGS: dict[str, list[str]] = {
    "flat_walk": ["synthetic", "walk", "flat"],
    "stairs_up": ["synthetic", "walk", "stairs"],
    "stairs_down": ["synthetic", "walk", "stairs"],
    "platform_step": ["synthetic", "walk", "platform"],
    "chair_sit": ["synthetic", "sit", "walk"],
}


_SUPPORT_TOLERANCE = 0.005  # m: a stance foot body whose sole is this close to a box top is on it


@dataclass(frozen=True)
class SynthConfig:
    """Settings shared by all kinds.

    Attributes:
        fps: frame rate of the generated motion (the paper's policy rate).
        height: stature of the humanoid the motion is generated for (m).
    """

    fps: float = 30.0
    height: float = 1.70


def make_clip(kind: str, seed: int, config: SynthConfig | None = None) -> tuple[list[Box], Motion, dict]:
    """A synthetic clip of ``kind`` (one of :data:`KINDS`), deterministic for ``seed``.

    Returns the scene's boxes (the floor first, its top at z = 0), the motion with ground-truth
    ``contacts`` (feet in stance; pelvis and thighs while seated) and a meta dict with
    ``source: "synthetic"``, the kind, the seed and every randomised parameter.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown synthetic clip kind {kind!r}; expected one of {KINDS}")
    cfg = config or SynthConfig()
    rng = np.random.default_rng([int(seed), KINDS.index(kind)])
    model = build_humanoid(HumanoidConfig(height=cfg.height))
    skel = Skeleton.from_model(model, cfg.height)
    gait = sample_gait(rng, curved=kind == "flat_walk")
    path = WalkPath(gait.curvature)
    plan = MotionPlan(feet=[(0.0, 0.0), (0.0, 0.0)])
    first = int(rng.integers(2))
    scene: dict = {}
    if kind == "flat_walk":
        boxes = [floor_box()]
        n = int(rng.integers(7, 10))
        plan.pose(0.0, PELVIS_AHEAD, 0.0, skel.pelvis_height - 0.012)
        targets = [(gait.step_length * (k - 0.5), 0.0) for k in range(1, n + 1)]
        add_walk(plan, 0.5, targets + [targets[-1]], first, gait, skel)
    elif kind in ("stairs_up", "stairs_down", "platform_step"):
        if kind == "platform_step":
            params = sample_platform_params(rng)
            boxes = platform_boxes(params)
            levels = [Level(params.start, params.start + params.length, params.height)]
            start_z = 0.0
            scene = {"platform": asdict(params)}
        else:
            descending = kind == "stairs_down"
            params = sample_stairs_params(rng, descending)
            boxes = stairs_boxes(params, descending)
            levels = stairs_levels(params, descending)
            start_z = params.top if descending else 0.0
            if descending:  # the walk starts on the landing
                levels = levels[1:]
            scene = {"stairs": asdict(params), "direction": "down" if descending else "up"}
        plan.feet = [(0.0, start_z), (0.0, start_z)]
        plan.pose(0.0, PELVIS_AHEAD, 0.0, start_z + skel.pelvis_height - 0.012)
        anchors = terrain_anchors(levels, start_z, 0.0, skel, kind == "stairs_up", gait.step_length)
        add_walk(plan, 0.5, footsteps(anchors, 0.0, gait.step_length), first, gait, skel)
    else:  # chair_sit
        params = sample_seat_params(rng)
        # Seat heights are for a 1.70 m adult; scale them with the humanoid's stature.
        params = replace(params, height=round(params.height * cfg.height / 1.70, 3))
        boxes = seat_boxes(params)
        scene = {"seat": asdict(params)}
        t_up = add_sit(plan, params, gait, skel, rng)
        away = float(rng.uniform(1.2, 1.8))
        targets = [(s, 0.0) for s in even_positions(0.0, away, gait.step_length)]
        add_walk(plan, t_up + 0.3, targets + [targets[-1]], first, gait, skel)
    frames = sample_plan(plan, path, boxes, skel, gait, cfg.fps)
    motion = plan_to_motion(frames, skel, gait, cfg.fps, model, boxes)
    contacts = np.zeros((motion.num_frames, len(BODY_NAMES)), dtype=bool)
    soles = sole_points(model, motion.qpos(), FEET)
    supported = np.nan_to_num(np.abs(support_tops(soles.reshape(-1, 3)[:, :2], boxes)
                                     - soles.reshape(-1, 3)[:, 2:3]), nan=np.inf).min(axis=1)
    supported = supported.reshape(soles.shape[:2]) < _SUPPORT_TOLERANCE
    for leg, bodies in enumerate(STANCE_BODIES):
        for body in bodies:  # a toe hanging over a nosing bears no weight
            contacts[:, BODY_NAMES.index(body)] = frames.stance[:, leg] & supported[:, FEET.index(body)]
    if kind == "chair_sit":
        seated = seat_contacts(motion, boxes, cfg.height)
        for body in SEAT_BODIES:
            contacts[:, BODY_NAMES.index(body)] = seated
    motion = Motion(fps=motion.fps, root_pos=motion.root_pos, root_quat=motion.root_quat,
                    dof_pos=motion.dof_pos, contacts=contacts)
    _check_ranges(motion)
    meta = {"source": "synthetic", "kind": kind, "seed": int(seed), "scene": scene, "gait": asdict(gait),
            "humanoid_height": cfg.height, "duration_s": motion.duration,
            "generator": "crisp_gym.synth.clips.make_clip"}
    return boxes, motion, meta


def _check_ranges(motion: Motion) -> None:
    """Every hinge within the humanoid's range (a generator bug otherwise)."""
    for i, name in enumerate(DOF_NAMES):
        body, axis = name.rsplit("_", 1)
        lo, hi = np.deg2rad(joint_range_deg(body)["xyz".index(axis)])
        values = motion.dof_pos[:, i]
        if values.min() < lo - 1e-6 or values.max() > hi + 1e-6:
            raise RuntimeError(f"hinge {name} leaves its range [{np.rad2deg(lo):.0f}, {np.rad2deg(hi):.0f}] "
                               f"deg: {np.rad2deg(values.min()):.1f}..{np.rad2deg(values.max()):.1f}")


def bundle_clips(out_dir: Path = BUNDLED_CLIPS, registry: Path = BUNDLED_REGISTRY) -> dict[str, Path]:
    """Write the bundled clips (:data:`BUNDLED`) and (re)write the bundled registry listing them.

    Returns name -> clip directory.
    """
    written = {}
    for name, (kind, seed) in BUNDLED.items():
        boxes, motion, meta = make_clip(kind, seed)
        written[name] = write_clip(Path(out_dir) / name, boxes, motion, {**meta, "name": name}, overwrite=True)
    write_registry(Path(registry), {name: (path, TAGS[name]) for name, path in written.items()},
                   header="Bundled clips, written by `crisp synth-clips`.")
    return written


@dataclass(frozen=True)
class SynthClipsArgs:
    """Regenerate the bundled clips and their registry, or (--kind) generate one more clip of a
    kind and seed and register it in the user registry.

    Attributes:
        out_dir: where the clip directories go (default: assets/clips, or the user clips folder with --kind).
        registry: registry file to (re)write (bundled clips).
        kind: generate one clip of this kind instead of the bundled set.
        seed: with --kind: the generator's seed.
        name: with --kind: the registered name (default: KIND_sSEED).
        overwrite: with --kind: replace an existing clip.
    """

    out_dir: Path | None = None
    registry: Path = BUNDLED_REGISTRY
    kind: Literal[KINDS] | None = None  # type: ignore[valid-type]
    seed: int = 0
    name: str | None = None
    overwrite: bool = False


def main(argv: list[str] | None = None) -> int:
    """``crisp synth-clips``: see :class:`SynthClipsArgs`."""
    args = tyro.cli(SynthClipsArgs, args=argv, prog="crisp synth-clips")
    if args.kind is None:
        for name, path in bundle_clips(args.out_dir or BUNDLED_CLIPS, args.registry).items():
            print(f"{name}: {path}")
        print(f"registry: {args.registry}")
        return 0
    name = check_clip_name(args.name or f"{args.kind}_s{args.seed}")
    out = (args.out_dir or user_clips_dir()) / name
    boxes, motion, meta = make_clip(args.kind, args.seed)
    write_clip(out, boxes, motion, {**meta, "name": name}, overwrite=args.overwrite)  # errors: crisp_gym.cli
    registry = register_clip(name, out, tags=["synthetic", "generated", args.kind])
    print(f"wrote clip '{name}' ({args.kind}, seed {args.seed}, {motion.num_frames} frames) to {out}\n"
          f"registered in {registry}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
