"""``crisp import-motion FILE --name NAME``: a flat-ground clip from a motion file.

Reads a BVH (retargeted onto the humanoid), SMPL-style axis-angle parameters (``.npz`` with
``global_orient``/``body_pose``/``transl``) or a ``motion.npz``, grounds it, writes a clip
(flat floor + the motion) and registers it in the user registry.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import platformdirs
import tyro

from crisp_gym.clip import write_clip
from crisp_gym.humanoid import build_humanoid
from crisp_gym.motion import Motion, ground
from crisp_gym.registry import register_clip
from crisp_gym.scene import floor_box


@dataclass(frozen=True)
class ImportMotionArgs:
    """Make a flat-ground clip from a motion file and register it."""

    file: Annotated[Path, tyro.conf.Positional]
    """BVH, SMPL-parameter npz or motion.npz."""
    name: str
    """Registered clip name."""
    output: Annotated[Path | None, tyro.conf.arg(aliases=["-o"])] = None
    """Clip directory (default: the user data dir's clips/NAME)."""
    fps: float = 30.0
    """Frame rate of the written motion."""
    smpl_fps: float = 30.0
    """Frame rate of SMPL parameter files (they carry none)."""
    up_axis: str = "y"
    """Up axis of BVH/SMPL input ("y" or "z")."""
    overwrite: bool = False
    """Replace an existing clip directory."""


def read_motion(path: Path, fps: float, smpl_fps: float = 30.0, up_axis: str = "y") -> Motion:
    """Load any supported motion file as a grounded :class:`Motion` at ``fps``."""
    if not path.is_file():
        raise FileNotFoundError(f"no motion file at {path}")
    suffix = path.suffix.lower()
    if suffix == ".bvh":
        from crisp_gym.bvh import load_bvh

        motion = load_bvh(path, up_axis=up_axis)
    elif suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            keys = set(data.files)
        if "dof_pos" in keys:
            motion = Motion.load(path)
        elif {"global_orient", "body_pose", "transl"} <= keys:
            from crisp_gym.smpl import load_smpl_params

            motion = load_smpl_params(path, fps=smpl_fps, up_axis=up_axis)
        else:
            raise ValueError(f"{path}: an npz motion needs motion.npz keys (dof_pos, ...) or SMPL keys "
                             f"(global_orient, body_pose, transl); found {sorted(keys)}")
    else:
        raise ValueError(f"{path}: unsupported motion file type {suffix!r} (expected .bvh or .npz)")
    motion = motion.resample(fps)
    # The BVH loader already grounds per frame from the stance feet; a second, constant grounding
    # would lift the whole clip onto its single lowest frame.
    return motion if suffix == ".bvh" else ground(motion, build_humanoid())


def import_motion(args: ImportMotionArgs) -> Path:
    motion = read_motion(args.file, args.fps, args.smpl_fps, args.up_axis)
    out = args.output or Path(platformdirs.user_data_dir("crisp-gym")) / "clips" / args.name
    meta = {"name": args.name, "source": "import-motion", "input": str(args.file.resolve()), "fps": motion.fps}
    write_clip(out, [floor_box()], motion, meta, overwrite=args.overwrite)
    registry = register_clip(args.name, out, tags=["imported", "flat"])
    print(f"wrote clip '{args.name}' ({motion.num_frames} frames at {motion.fps:g} fps) to {out}\n"
          f"registered in {registry}")
    return out


def main(argv: list[str] | None = None) -> int:
    import_motion(tyro.cli(ImportMotionArgs, args=argv, prog="crisp import-motion"))
    return 0
