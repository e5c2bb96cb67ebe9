"""``crisp reconstruct``: a depth video and a human motion in, a simulation-ready clip out.

Stages (paper, Algorithm 1), each timed into ``meta.json``:

1. **read**: :func:`crisp_gym.reconstruct.io.read_frames` (MegaSAM-style npz or an RGB-D folder) and
   :func:`crisp_gym.reconstruct.io.read_motion` (camera-frame SMPL parameters, BVH or ``motion.npz``);
2. **align**: :func:`crisp_gym.reconstruct.align.align` removes the person, recovers the metric scale from
   the human, gravity from the human and the floor, and puts the floor at z = 0;
3. **planes**: :func:`crisp_gym.reconstruct.planes.fit_planes` turns the static scene into box primitives;
4. **contact**: :mod:`crisp_gym.reconstruct.contact` adds the supports the human's contacts imply and the
   camera never saw (``--contacts kinematic`` from the motion, a file, or ``none``);
5. **write**: the clip directory (``scene.xml``, ``motion.npz`` in the scene's frame,
   ``primitives.json``, ``meta.json``), written to a temporary directory and renamed, so an
   interrupted run leaves nothing half-written.

Without a motion there is nothing to track: the output is a scene directory (``scene.xml``,
``primitives.json``, ``meta.json``) and ``--metric`` is required, since the scale comes from the
human.
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

from crisp_gym.atomic import atomic_directory
from crisp_gym.clip import write_clip
from crisp_gym.humanoid import build_humanoid
from crisp_gym.motion import Motion, compute_kinematics
from crisp_gym.reconstruct.align import AlignConfig, Alignment, align, transform_motion
from crisp_gym.reconstruct.contact import (
    CompletionResult,
    ContactConfig,
    ContactSource,
    contact_completion,
)
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.io import (
    MotionInput,
    RgbdFolderConfig,
    check_video_fps,
    is_plain_video,
    read_frames,
    read_motion,
    read_video,
)
from crisp_gym.reconstruct.planes import PlaneFit, PlaneFitConfig, fit_planes
from crisp_gym.reconstruct.report_page import write_report_page
from crisp_gym.registry import check_clip_name, plain_clip_name, register_clip
from crisp_gym.scene import Box, save_primitives, write_scene_xml


@dataclass(frozen=True)
class ReconstructConfig:
    """Every setting of the pipeline, one frozen dataclass per stage (defaults: the paper's)."""

    align: AlignConfig = field(default_factory=AlignConfig)
    planes: PlaneFitConfig = field(default_factory=PlaneFitConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)


@dataclass(frozen=True)
class Reconstruction:
    """What :func:`reconstruct` returns.

    Attributes:
        boxes: the scene: planar primitives, then contact primitives.
        motion: the motion in the scene's frame (``None`` without one).
        alignment: how the input was brought into the world.
        planes: the planar fit with its diagnostics.
        completion: the contact completion (``None`` with ``contacts="none"`` or no motion).
        timings: seconds per stage.
        frames: the aligned input (metric, in the scene's frame, person removed), e.g. for a
            baseline fused from the same depth.
        frame: ``"world"`` (gravity-aligned, floor at z = 0, origin and yaw the pipeline's) or
            ``"input"`` (the input's own frame, scaled to metres: see :func:`in_input_frame`).
    """

    boxes: list[Box]
    motion: Motion | None
    alignment: Alignment
    planes: PlaneFit
    completion: CompletionResult | None
    timings: dict[str, float]
    frames: Frames
    frame: Literal["world", "input"] = "world"

    def meta(self) -> dict:
        """The JSON-ready provenance for ``meta.json``."""
        counts = {"planar": sum(b.source == "planar" for b in self.boxes),
                  "contact": sum(b.source == "contact" for b in self.boxes)}
        meta = {
            "source": "reconstruct",
            "frame": self.frame,
            "scale": self.alignment.scale,
            "alignment": self.alignment.to_json(),
            "timings": {k: round(v, 3) for k, v in self.timings.items()},
            "counts": counts | {"segments": self.planes.segments, "groups": self.planes.groups,
                                "dropped_points": self.planes.dropped},
            "plane_timings": {k: round(v, 3) for k, v in self.planes.timings.items()},
        }
        if self.completion is not None:
            meta["contact_primitives"] = self.completion.meta()
            meta["contacts"] = {"supported": self.completion.supported, "dropped": self.completion.dropped}
        return meta


INPUT_FRAME_MAX_TILT_DEG = 5.0
"""``--keep-input-frame`` needs an input whose +z is up within this angle (simulation pulls along −z)."""


def in_input_frame(result: Reconstruction) -> Reconstruction:
    """``result`` expressed in the input's own frame (scaled to metres) instead of the world the
    pipeline builds, whose origin and yaw it chooses: for clips that must match a map the input's
    poses are in (a robot's, a SLAM system's). The input must already be gravity-aligned: z up."""
    input_from_world = np.linalg.inv(result.alignment.world_from_input)
    up = input_from_world[:3, :3] @ np.array([0.0, 0.0, 1.0])
    tilt = float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))
    if tilt > INPUT_FRAME_MAX_TILT_DEG:
        raise ValueError(f"--keep-input-frame needs an input whose z axis points up; in this input the floor's normal "
                         f"is {tilt:.1f}° from +z (at most {INPUT_FRAME_MAX_TILT_DEG:g}°): leave the option out to "
                         f"get the gravity-aligned world, or give poses in a z-up frame")
    motion = None if result.motion is None else transform_motion(result.motion, input_from_world)
    return replace(result, boxes=[b.transformed(input_from_world) for b in result.boxes], motion=motion,
                   frames=result.frames.transformed(input_from_world), frame="input")





def reconstruct(frames: Frames, motion: MotionInput | None = None, config: ReconstructConfig | None = None,
                contacts: ContactSource = "kinematic", metric: bool = False, vertex_map: Path | None = None,
                progress: bool = True) -> Reconstruction:
    """Run align → planes → contact on frames already read (see the module docstring)."""
    cfg = config or ReconstructConfig()
    timings: dict[str, float] = {}
    start = time.perf_counter()
    aligned = align(frames, motion, cfg.align, metric=metric)
    timings["align"] = time.perf_counter() - start

    start = time.perf_counter()
    pelvis = None
    if aligned.motion is not None:
        pelvis = compute_kinematics(aligned.motion, build_humanoid()).body_pos[:, 0]
    planes = fit_planes(aligned.frames, pelvis, cfg.planes, progress=progress)
    timings["planes"] = time.perf_counter() - start

    start = time.perf_counter()
    completion = None
    if aligned.motion is not None:
        completion = contact_completion(aligned.motion, planes.boxes, contacts, cfg.contact, vertex_map)
    timings["contact"] = time.perf_counter() - start
    boxes = list(planes.boxes) + ([] if completion is None else list(completion.boxes))
    return Reconstruction(boxes=boxes, motion=aligned.motion, alignment=aligned.alignment, planes=planes,
                          completion=completion, timings=timings, frames=aligned.frames)


def no_box_reason(result: Reconstruction, frames: Frames) -> str:
    """Why a reconstruction produced no primitive, from the planar fit's counts, for the user."""
    planes, cfg = result.planes, ReconstructConfig().planes
    valid = float(frames.valid.mean())
    if planes.segments == 0:
        return (f"no box survived: no frame had a planar segment ({frames.num_frames} frames, {100 * valid:.0f} % "
                f"valid depth pixels); is the depth a depth map, in metres (or rescaled by the motion)?")
    return (f"no box survived: {planes.segments} planar segments formed {planes.groups} planar groups, none "
            f"seen in at least {cfg.min_group_frames} of the {frames.num_frames} frames (or covering "
            f"{100 * cfg.single_view_share:.0f} % of one) with {cfg.min_group_points} inlier points and a box's size "
            f"(filtered before fitting: {planes.dropped}); a short or nearly still video sees each surface in few "
            f"frames")


def write_scene_dir(directory: Path, boxes: list[Box], meta: dict, overwrite: bool = False) -> Path:
    """A scene-only directory (no motion): ``scene.xml``, ``primitives.json``, ``meta.json``, atomically."""
    with atomic_directory(directory, overwrite) as tmp:
        write_scene_xml(boxes, tmp / "scene.xml")
        save_primitives(boxes, tmp / "primitives.json")
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2))
    return Path(directory)


@dataclass
class ReconstructArgs:
    """Reconstruct a simulation-ready clip from a depth video and the human's motion, or from a plain video."""

    input: tyro.conf.Positional[Path]
    """A MegaSAM-style npz, an RGB-D folder (TUM / Redwood), or a plain video (mp4/mov or an image folder)."""
    motion: Path | None = None
    """The human's motion: camera-frame SMPL parameters (GVHMR-style npz/.pt), a BVH or a motion.npz."""
    motion_frame: Literal["camera", "camera0"] = "camera"
    """Frame of SMPL parameters: each frame in its own camera ("camera", GVHMR's incam) or all in the first."""
    name: str | None = None
    """Clip name (default: the input's stem)."""
    output: Annotated[Path | None, tyro.conf.arg(aliases=["-o"])] = None
    """Output directory (default: ./clips/NAME)."""
    contacts: str = "kinematic"
    """Contact source: "kinematic" (from the motion), "none", or a contacts file (contacts.npz or per-vertex npz)."""
    vertex_map: Path | None = None
    """For per-vertex contact files: an npz with vertex_body (6890,) mapping SMPL vertices to bodies."""
    metric: bool = False
    """Trust the depth as metres (required without --motion)."""
    keep_input_frame: bool = False
    """Write the clip in the input's own frame (which must be z up), not a world whose origin and yaw the
    pipeline picks: for clips that must line up with the map the poses came from."""
    intrinsics: tuple[float, float, float, float] | None = None
    """RGB-D folders: FX FY CX CY of the depth images in pixels (default: the folder's camera file or layout)."""
    depth_scale: float | None = None
    """RGB-D folders: depth image units per metre, e.g. 1000 for millimetres (default: as for --intrinsics)."""
    fps: float | None = None
    """Plain videos: the frame rate of an image folder (a video file's own is read from it; default 30)."""
    max_side: int = 960
    """Plain videos: frames are downscaled so their long side is at most this many pixels."""
    fixed_camera: bool = False
    """Plain videos: the camera stood still (a tripod): no structure from motion, the scene from the person alone."""
    person_height: float | None = None
    """Plain videos: the person's stature in metres, when known; the scene is scaled to it (default: the
    body size MediaPipe gives them, recorded in meta.json as implied_stature_m)."""
    cache: Path | None = None
    """Plain videos: a folder keeping the person track and the camera solve (over 90 % of the time); a re-run
    on the same frames with the same camera settings reuses them."""
    seed: int = 0
    """Plain videos: seed of the RANSAC fits and COLMAP (runs are reproducible)."""
    register: bool = False
    """Add the clip to the user registry under NAME."""
    overwrite: bool = False
    """Replace an existing output directory."""


def _check_writable(out: Path) -> None:
    """ValueError unless a folder can be made where ``out``'s nearest existing ancestor is (tried
    for real: permission bits do not say it for root or for filesystems such as /proc)."""
    parent = next(p for p in out.absolute().parents if p.exists())
    try:
        probe = Path(tempfile.mkdtemp(prefix=".crisp-write-check-", dir=parent))
    except OSError as err:
        raise ValueError(f"cannot write {out}: {parent} does not take new folders ({err.strerror})") from None
    probe.rmdir()


def run(args: ReconstructArgs) -> Path:
    """Read, reconstruct and write; returns the output directory."""
    # Name and output are checked before any work: a bad one found after minutes of fitting loses them.
    name = check_clip_name(args.name) if args.name is not None else plain_clip_name(args.input.stem)
    out = Path(args.output) if args.output is not None else Path("clips") / name
    if out.exists() and not args.overwrite:
        raise FileExistsError(f"{out} exists; pass --overwrite to replace it")
    _check_writable(out)
    contacts: ContactSource = args.contacts if args.contacts in ("kinematic", "none") else Path(args.contacts)
    if isinstance(contacts, Path) and not contacts.is_file():
        raise FileNotFoundError(f"--contacts {contacts}: expected 'kinematic', 'none' or an existing contacts file")

    if args.fps is not None:
        check_video_fps(args.fps, "--fps")
    if args.motion is None and is_plain_video(args.input):
        if args.keep_input_frame:
            raise ValueError("--keep-input-frame applies to depth inputs with poses; a plain video has no frame "
                             "of its own")
        return run_video(args, name, out)
    start = time.perf_counter()
    frames = read_frames(args.input, rgbd=RgbdFolderConfig(intrinsics=args.intrinsics, depth_scale=args.depth_scale))
    motion = None if args.motion is None else read_motion(args.motion, frame=args.motion_frame)
    read_time = time.perf_counter() - start
    result = reconstruct(frames, motion, contacts=contacts, metric=args.metric, vertex_map=args.vertex_map)
    if not result.boxes:
        raise ValueError(no_box_reason(result, frames))
    if args.keep_input_frame:
        result = in_input_frame(result)
    meta = result.meta() | {"name": name, "input": str(args.input.resolve()),
                            "motion_input": None if args.motion is None else str(args.motion.resolve()),
                            "contact_source": str(args.contacts), "fps": frames.fps,
                            "frames": frames.num_frames, "image_size": list(frames.image_size)}
    meta["timings"] = {"read": round(read_time, 3)} | meta["timings"]

    if result.motion is None:
        write_scene_dir(out, result.boxes, meta, overwrite=args.overwrite)
        print(f"wrote scene '{name}' ({len(result.boxes)} primitives) to {out}")
        return out
    write_clip(out, result.boxes, result.motion, meta, overwrite=args.overwrite,
               write_extras=lambda tmp: write_report_page(tmp, meta, result.boxes, result.motion))
    counts = meta["counts"]
    print(f"wrote clip '{name}': {counts['planar']} planar + {counts['contact']} contact primitives, "
          f"scale {result.alignment.scale:.3f}, to {out}")
    if args.register:
        print(f"registered in {register_clip(name, out, tags=['reconstructed'])}")
    return out


def run_video(args: ReconstructArgs, name: str, out: Path) -> Path:
    """The plain-video path (:mod:`crisp_gym.reconstruct.video`): clip, ``meta.json`` flags, ``comparison.mp4``,
    ``report.html``."""
    from crisp_gym.reconstruct.video import SfmConfig, VideoConfig, check_video_extras, reconstruct_video  # noqa: PLC0415
    from crisp_gym.reconstruct.video_report import write_comparison  # noqa: PLC0415

    # Settings and extras are checked before reading minutes of video.
    config = VideoConfig(sfm=SfmConfig(seed=args.seed), use_sfm=not args.fixed_camera,
                         person_height=args.person_height)
    check_video_extras(use_sfm=not args.fixed_camera)
    start = time.perf_counter()
    frames, fps = read_video(args.input, max_side=args.max_side, fps=args.fps)
    read_time = time.perf_counter() - start
    result = reconstruct_video(frames, fps, config, seed=args.seed, cache=args.cache)
    meta = {"name": name, "source": "reconstruct-video", "input": str(args.input.resolve()), "video_fps": fps,
            "image_size": [int(frames.shape[2]), int(frames.shape[1])], "quality": result.flags,
            "timings": {"read": round(read_time, 3)} | {k: round(v, 3) for k, v in result.timings.items()},
            "intrinsic": result.cameras.intrinsic.round(3).tolist()}
    if result.completion is not None:
        meta["contact_primitives"] = result.completion.meta()
    start = time.perf_counter()

    def extras(tmp: Path) -> None:
        write_comparison(result, frames, fps, tmp / "comparison.mp4")
        write_report_page(tmp, meta, result.boxes, result.motion, video="comparison.mp4")

    write_clip(out, result.boxes, result.motion, meta, overwrite=args.overwrite, write_extras=extras)
    print(f"wrote clip '{name}': {len(result.boxes)} primitives, {result.motion.num_frames} frames, scale "
          f"{result.scale:.4g} m per SfM unit{' (fixed camera)' if result.cameras.static else ''}, to {out} "
          f"(comparison video in {time.perf_counter() - start:.0f} s)")
    if args.register:
        print(f"registered in {register_clip(name, out, tags=['reconstructed', 'video'])}")
    return out


def main(argv: list[str] | None = None) -> int:
    run(tyro.cli(ReconstructArgs, args=argv, prog="crisp reconstruct"))
    return 0
