"""``crisp import-motion FILE_OR_FOLDER --name NAME``: flat-ground clips from motion files.

Each file becomes a clip (flat floor + the motion) registered in the user registry; a folder
becomes one clip per motion file in it, named ``NAME_<file stem>``. Formats, told apart by
extension and by the arrays an npz holds:

==================  =================================================================================
format              recognised by
==================  =================================================================================
BVH                 ``.bvh`` (retargeted onto the humanoid, see :mod:`crisp_gym.bvh`)
AMASS               ``.npz`` with ``poses`` (T,72/156/165) and ``trans``; frame rate ``mocap_framerate``
SMPL parameters     ``.npz`` with ``global_orient``, ``body_pose``, ``transl`` (GVHMR and others)
PHC / SMPLSim       ``.npz`` with ``pose_aa`` (T,24,3) and ``trans`` (our ``smpl`` export)
BeyondMimic/mjlab   ``.npz`` with ``joint_pos``, ``body_pos_w``, ``body_quat_w``, ``fps``
ProtoMotions        ``.motion`` (torch-saved ``dof_pos``, ``rigid_body_pos``/``_rot``, ``fps``; read
                    without running code, see :mod:`crisp_gym.protomotions`)
``fields``/``qpos``  ``.npz`` of ``crisp export --format npz``
``motion.npz``      ``.npz`` with ``root_pos``, ``root_quat``, ``dof_pos`` (a clip's own motion)
CSV                 ``.csv`` of ``crisp export --format csv``
==================  =================================================================================

The source frame rate is the file's own (``--source-fps`` overrides it, and is needed for SMPL
parameter files that carry none); the clip is resampled to ``--fps``. The up axis of BVH and
SMPL-family files is detected unless given (:func:`crisp_gym.bvh.detect_up_axis`,
:func:`crisp_gym.smpl.detect_up_axis`) and reported. Every import is grounded frame by frame from
its planted feet (:func:`crisp_gym.motion.ground_stance`; captures also get their planted feet
laid flat, :func:`crisp_gym.motion.level_feet`; with ``--plant-feet`` a planted foot left above
the floor is also brought down onto it by bending its leg, :func:`crisp_gym.motion.plant_feet`),
or by one offset with ``--grounding constant``. A BVH capture's joints are fitted into the
humanoid's ranges, each foot kept where it was (:func:`crisp_gym.motion.fit_into_range`, reported);
the other formats' joints are read as decomposed or written. With ``--plant-support`` a foot that
hovers where the motion's centre of pressure needs it on the floor is put there too
(:func:`crisp_gym.balance.plant_supporting_feet`).

``--frames START:STOP`` keeps frames ``START`` to ``STOP - 1`` of the clip as written at ``--fps``
(either bound may be left out; a negative one counts from the end). The cut comes last, after
grounding and planting over the whole motion, so a segment holds exactly those frames of the whole
import: a motion library can practise one hard move beside the whole clip
(``docs/training.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Literal

import mujoco
import numpy as np
import tyro
from tqdm.auto import tqdm

from crisp_gym.balance import Followability, followability, plant_supporting_feet
from crisp_gym.clip import write_clip
from crisp_gym.file_errors import reading
from crisp_gym.humanoid import build_humanoid
from crisp_gym.motion import Motion, StanceGrounding, check_plausible, ground, ground_stance, level_feet
from crisp_gym.npz import read_npz
from crisp_gym.registry import check_clip_name, plain_clip_name, register_clip, user_clips_dir
from crisp_gym.scene import floor_box

MOTION_SUFFIXES = (".bvh", ".npz", ".csv", ".motion")
"""File types a folder import picks up."""

Grounding = Literal["stance", "constant"]
_MAX_FPS = 1000.0  # frame rates beyond any capture's are a wrong header, not a motion
_MAX_FRAMES = 1e6  # frames of a written clip: 9 hours at 30 fps
# m: a per-frame correction spanning nearly its whole range (2 x max_shift) is following terrain, not a
# capture's drifting floor (CMU 131_01's, the largest seen, spans 14.6 cm)
_FLAT_GROUND_SPREAD = 2 * StanceGrounding().max_shift - 0.01
UpAxis = Literal["auto", "x", "y", "z"]


@dataclass(frozen=True)
class ImportMotionArgs:
    """Make flat-ground clips from motion files and register them."""

    file: Annotated[Path, tyro.conf.Positional]
    """A motion file (module docstring for the formats), or a folder of them."""
    name: str
    """Registered clip name; for a folder, the prefix of NAME_<file stem>."""
    output: Annotated[Path | None, tyro.conf.arg(aliases=["-o"])] = None
    """Clip directory (default: the user data dir's clips/NAME); for a folder, the parent of the clips."""
    fps: float = 30.0
    """Frame rate of the written motion."""
    source_fps: float | None = None
    """Frame rate of the input (default: the file's own)."""
    up_axis: UpAxis = "auto"
    """Up axis of BVH and SMPL-family input (auto: detected and reported)."""
    grounding: Grounding = "stance"
    """stance: planted feet on the floor frame by frame; constant: one vertical offset."""
    plant_feet: bool = False
    """With stance grounding, bend a leg whose planted foot stands above the floor (and above the
    other planted foot) until it stands on it (off by default: the legs as read track as well)."""
    plant_support: bool = False
    """Where the ground must carry the body, stand the foot (or feet) its centre of pressure calls
    for on the floor when it hovers less than 10 cm above it (a capture's late landing or sliding
    foot; crisp_gym.balance.plant_supporting_feet)."""
    frames: str | None = None
    """Keep only frames START:STOP of the written motion (Python slice bounds at --fps, end excluded,
    e.g. 60:110), cut after grounding and planting: exactly those frames of the whole import."""
    overwrite: bool = False
    """Replace existing clip directories."""


@dataclass(frozen=True)
class ReadMotion:
    """A motion file read by :func:`read_motion`, with what was found and done.

    Attributes:
        motion: the grounded motion at the requested frame rate.
        source_format: the detected format (module docstring).
        source_fps: the input's frame rate (the file's own or the override).
        up_axis: the input's up axis, or ``None`` for formats that are z-up by definition.
        ground_shift: (min, max) metres added to the root height by grounding.
        range_fit: (share of hinge values changed, largest joint turn in degrees) by fitting a BVH
            capture's joints into the humanoid's ranges (``(0, 0)`` for the other formats).
        kept: for a segment (:meth:`segment`), its ``(start, stop)`` frames and the whole import's
            frame count; ``None`` for the whole motion.
    """

    motion: Motion
    source_format: str
    source_fps: float
    up_axis: str | None
    ground_shift: tuple[float, float]
    range_fit: tuple[float, float] = (0.0, 0.0)
    kept: tuple[int, int, int] | None = None

    def segment(self, frames: tuple[int | None, int | None]) -> ReadMotion:
        """Frames ``start:stop`` of the motion (:func:`parse_frame_range`'s bounds), checked
        against its length: a bound beyond it is an error, not clamped as a Python slice would."""
        total = self.motion.num_frames
        for bound in frames:
            if bound is not None and not -total <= bound <= total:
                raise ValueError(f"--frames: frame {bound} is outside the motion's {total} frames at "
                                 f"{self.motion.fps:g} fps")
        start, stop, _ = slice(*frames).indices(total)
        if stop - start < 2:
            raise ValueError(f"--frames keeps {max(stop - start, 0)} of the motion's {total} frames "
                             f"({start}:{stop}); a clip needs at least 2")
        return replace(self, motion=self.motion.slice(start, stop), kept=(start, stop, total))

    def describe(self) -> str:
        """One line for the user: what was read and how it was grounded (and a warning when the
        per-frame grounding moved the body by more than a capture's floor drift)."""
        axis = f", {self.up_axis} up" if self.up_axis else ""
        low, high = (100 * v for v in self.ground_shift)
        shift = f"{low:+.1f} cm" if np.isclose(low, high, atol=0.05) else f"{low:+.1f} to {high:+.1f} cm"
        frames = self.motion.num_frames if self.kept is None else self.kept[2]
        line = (f"{self.source_format}{axis}, {self.source_fps:g} fps -> {frames} frames at "
                f"{self.motion.fps:g} fps, grounded by {shift}")
        if self.range_fit[0] > 0:
            line += (f", {100 * self.range_fit[0]:.1f} % of hinge values fitted into the joint ranges (a joint "
                     f"turned by up to {self.range_fit[1]:.0f}°)")
        if self.kept is not None:
            line += f", kept frames {self.kept[0]}:{self.kept[1]}"
        if high - low > 100 * _FLAT_GROUND_SPREAD:
            line += (f"\n  warning: the grounding correction spans {high - low:.0f} cm, nearly its limit; the clip's "
                     f"floor is flat, so a motion on steps or slopes was flattened: --grounding constant keeps it")
        return line


def parse_frame_range(text: str) -> tuple[int | None, int | None]:
    """``--frames``' ``START:STOP`` as slice bounds (``None`` where left out); checked before
    any work, the bounds against the motion by :meth:`ReadMotion.segment`."""
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        start, stop = (int(part) if part.strip() else None for part in parts)
    except ValueError:
        raise ValueError(f"--frames takes START:STOP in frames at --fps (e.g. 60:110 or 60:), got {text!r}") from None
    return start, stop


def _npz_keys(path: Path) -> set[str]:
    return set(read_npz(path, "motion file", skip_objects=True))


def _read_source(path: Path, source_fps: float | None, up_axis: str, model: mujoco.MjModel,
                 grounding: StanceGrounding | None
                 ) -> tuple[Motion, str, str | None, np.ndarray | None, tuple[float, float]]:
    """The motion as the file has it, its format, its up axis and, for BVH (whose retarget
    grounds as it lays the feet flat and fits the joints into range), the grounding offset
    already applied and what the range fit changed (:attr:`ReadMotion.range_fit`)."""
    suffix = path.suffix.lower()
    if suffix == ".bvh":
        from crisp_gym.bvh import parse_bvh, retarget_bvh

        clip = parse_bvh(path)
        if source_fps is not None:
            clip = replace(clip, frame_time=1.0 / source_fps)
        result = retarget_bvh(clip, up_axis=up_axis, model=model, grounding=grounding)
        return (result.motion, "BVH", result.up_axis, result.ground_offset,
                (result.clipped_fraction, result.max_clip_deg))
    if suffix == ".csv":
        from crisp_gym.export.motion_formats import read_motion_csv

        return read_motion_csv(path), "CSV", None, None, (0.0, 0.0)
    if suffix == ".motion":
        from crisp_gym.protomotions import read_protomotions

        motion = read_protomotions(path)
        motion = motion if grounding is None else level_feet(motion, model, grounding)
        return motion, "ProtoMotions", None, None, (0.0, 0.0)
    if suffix != ".npz":
        raise ValueError(f"{path}: unsupported motion file type {suffix!r} (expected {', '.join(MOTION_SUFFIXES)})")
    keys = _npz_keys(path)
    if keys & {"global_orient", "poses", "pose_aa"}:
        from crisp_gym.smpl import detect_up_axis, load_smpl_params, read_smpl_source, stored_fps

        params = read_smpl_source(path)
        if source_fps is None and stored_fps(params) is None:
            raise ValueError(f"{path} carries no frame rate (no fps or mocap_framerate entry): pass --source-fps")
        axis = detect_up_axis(params)[0] if up_axis == "auto" else up_axis
        fmt = "AMASS" if "poses" in keys else "PHC SMPL" if "pose_aa" in keys else "SMPL parameters"
        motion = load_smpl_params(params, fps=source_fps, up_axis=axis, to_floor=False)
        return (motion if grounding is None else level_feet(motion, model, grounding)), fmt, axis, None, (0.0, 0.0)
    if {"root_pos", "root_quat", "dof_pos"} <= keys:
        return Motion.load(path), "motion.npz", None, None, (0.0, 0.0)
    from crisp_gym.export.motion_formats import read_motion_npz

    motion = read_motion_npz(path)
    return motion, "BeyondMimic" if "joint_pos" in keys else "crisp npz", None, None, (0.0, 0.0)


def read_motion(path: Path, fps: float = 30.0, source_fps: float | None = None, up_axis: str = "auto",
                grounding: str = "stance", model: mujoco.MjModel | None = None,
                plant_feet: bool = False, plant_support: bool = False) -> ReadMotion:
    """Load any supported motion file (module docstring) as a grounded :class:`Motion` at ``fps``
    (``plant_feet``: see :attr:`crisp_gym.motion.StanceGrounding.plant`; ``plant_support``:
    :func:`crisp_gym.balance.plant_supporting_feet`, after grounding)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no motion file at {path}")
    for label, rate in (("fps", fps), ("source fps", source_fps)):
        if rate is not None and not (np.isfinite(rate) and 0 < rate <= _MAX_FPS):
            raise ValueError(f"{label} must be a frame rate in (0, {_MAX_FPS:g}], got {rate}")
    if grounding not in ("stance", "constant"):
        raise ValueError(f"grounding must be 'stance' or 'constant', got {grounding!r}")
    model = model if model is not None else build_humanoid()
    stance = StanceGrounding(plant=plant_feet) if grounding == "stance" else None
    with reading(path, "motion file"):
        motion, fmt, axis, offset, range_fit = _read_source(path, source_fps, up_axis, model, stance)
    if source_fps is not None:
        motion = replace(motion, fps=source_fps)
    rate = motion.fps
    if not rate <= _MAX_FPS:
        raise ValueError(f"{path}: a frame rate of {rate:g} fps is not a capture's (at most {_MAX_FPS:g}); "
                         f"pass --source-fps if the file's is wrong")
    frames = (motion.num_frames - 1) * fps / rate + 1  # checked before resampling allocates them
    if frames > _MAX_FRAMES:
        raise ValueError(f"{path}: {motion.num_frames} frames at {rate:g} fps are {frames:.3g} frames at {fps:g} fps "
                         f"(at most {_MAX_FRAMES:.0e}); is the frame rate ({rate:g} fps) right? --source-fps sets it")
    try:
        check_plausible(motion)
    except ValueError as err:
        raise ValueError(f"{path}: no body can do this motion: {err}") from None
    motion = motion.resample(fps)
    if offset is None:
        grounded = ground(motion, model) if stance is None else ground_stance(motion, model, stance)
        offset = grounded.root_pos[:, 2] - motion.root_pos[:, 2]
        motion = grounded
    if plant_support:
        motion = plant_supporting_feet(motion, model)
    return ReadMotion(motion, fmt, rate, axis, (float(offset.min()), float(offset.max())), range_fit)


def clip_name_for(prefix: str, file: Path) -> str:
    """``PREFIX_<stem>``, made a plain clip name (:func:`crisp_gym.registry.plain_clip_name`)."""
    return plain_clip_name(f"{prefix}_{file.stem}")


def import_file(file: Path, name: str, output: Path, args: ImportMotionArgs,
                model: mujoco.MjModel) -> tuple[ReadMotion, Followability]:
    """Read ``file``, write it as clip ``name`` at ``output`` and register it; also say where
    its body cannot balance on its feet (``meta.json``'s ``followability``)."""
    read = read_motion(file, args.fps, args.source_fps, args.up_axis, args.grounding, model, args.plant_feet,
                       args.plant_support)
    if args.frames is not None:
        read = read.segment(parse_frame_range(args.frames))
    follow = followability(read.motion)
    meta = {"name": name, "source": "import-motion", "input": str(file.resolve()), "fps": read.motion.fps,
            "source_format": read.source_format, "source_fps": read.source_fps, "up_axis": read.up_axis,
            "grounding": args.grounding, "plant_feet": args.plant_feet,
            "plant_support": args.plant_support, "followability": follow.to_json()}
    if read.kept is not None:
        meta["frames"] = list(read.kept[:2])
    write_clip(output, [floor_box()], read.motion, meta, overwrite=args.overwrite)
    register_clip(name, output, tags=["imported", "flat"])
    return read, follow


def import_motion(args: ImportMotionArgs) -> list[Path]:
    """Run ``crisp import-motion``; returns the clip directories written."""
    check_clip_name(args.name)
    if args.frames is not None:
        parse_frame_range(args.frames)
    clips_dir = user_clips_dir()
    model = build_humanoid()
    if not args.file.is_dir():
        out = args.output or clips_dir / args.name
        read, follow = import_file(args.file, args.name, out, args, model)
        print(f"read {args.file.name}: {read.describe()}\n{follow.describe()}\nwrote clip '{args.name}' to {out}")
        return [out]
    files = sorted(f for f in args.file.iterdir() if f.is_file() and f.suffix.lower() in MOTION_SUFFIXES)
    if not files:
        raise FileNotFoundError(f"{args.file} holds no motion files ({', '.join(MOTION_SUFFIXES)})")
    written, failed = [], []
    for file in tqdm(files, desc="import", unit="file"):
        name = clip_name_for(args.name, file)
        out = (args.output or clips_dir) / name
        try:
            read, follow = import_file(file, name, out, args, model)
        except (ValueError, FileNotFoundError, FileExistsError) as err:
            failed.append(f"{file.name}: {err}")
            continue
        tqdm.write(f"{name}: {read.describe()}; {follow.describe(max_spans=3)}")
        written.append(out)
    print(f"imported {len(written)} of {len(files)} files from {args.file}")
    if failed:
        raise ValueError("not imported:\n  " + "\n  ".join(failed))
    return written


def main(argv: list[str] | None = None) -> int:
    """``crisp import-motion`` (user errors are reported by :mod:`crisp_gym.cli`)."""
    import_motion(tyro.cli(ImportMotionArgs, args=argv, prog="crisp import-motion"))
    return 0
