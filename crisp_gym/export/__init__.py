"""Export clips and trained policies for other stacks: ``crisp export SOURCE --format F [F ...] -o OUT``.

SOURCE is a clip (registered name or directory) for the clip formats, or a ``crisp train``
checkpoint (file or run directory) for the policy formats. Each format writes into its own
folder of OUT:

===============  ==================================  ===========================================================
format           files                               for
===============  ==================================  ===========================================================
``mjcf``         ``mjcf/scene.xml``, ``track.xml``,  MuJoCo (the env's model with keyframes; steps identically)
                 ``motion.npz``
``mjx``          ``mjx/...`` (same names)            MJX, MuJoCo Playground, Brax (floor as a plane)
``dm_control``   ``dm_control/arena.xml``,           ``dm_control.mjcf`` (arena + walker to attach)
                 ``walker.xml``, ``track.xml``,
                 ``motion.npz``
``urdf``         ``urdf/scene.urdf``,                Isaac Gym/Lab, PyBullet, Genesis
                 ``humanoid.urdf``,
                 ``humanoid_actuators.json``
``glb``/``obj``  ``mesh/scene.glb`` / ``scene.obj``  viewers, mesh-based simulators
``csv``          ``motion/motion.csv``               spreadsheets, any language
``npz``          ``motion/motion_fields.npz``,       Isaac-style per-field arrays; MuJoCo qpos/qvel
                 ``motion/motion_qpos.npz``
``smpl``         ``motion/motion_smpl.npz``          SMPL trackers (``pose_aa``/``trans`` at 30 fps)
``amass``        ``motion/motion_amass.npz``         AMASS readers: ProtoMotions, PHC converters
                                                     (``poses``/``trans``/``betas`` at 30 fps, z up)
``beyondmimic``  ``motion/motion_beyondmimic.npz``   BeyondMimic / mjlab tracking (joint and world
                                                     body states with velocities)
``onnx``         ``policy/policy.onnx``, ``.json``   onnxruntime on the robot
``torchscript``  ``policy/policy.pt``, ``.json``     libtorch / PyTorch without this package
===============  ==================================  ===========================================================

``all`` is every clip format. The modules: :mod:`~crisp_gym.export.mjcf`,
:mod:`~crisp_gym.export.urdf`, :mod:`~crisp_gym.export.meshes`,
:mod:`~crisp_gym.export.motion_formats`, :mod:`~crisp_gym.export.policy`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro
from tqdm.auto import tqdm

from crisp_gym.atomic import atomic_directory
from crisp_gym.clip import Clip
from crisp_gym.export.meshes import write_scene_mesh
from crisp_gym.export.mjcf import MjcfExportConfig, write_mjcf
from crisp_gym.export.motion_formats import write_motion_csv, write_motion_npz
from crisp_gym.export.urdf import UrdfConfig, write_urdf
from crisp_gym.registry import load_clip

Format = Literal["all", "mjcf", "mjx", "dm_control", "urdf", "glb", "obj", "csv", "npz", "smpl", "amass",
                 "beyondmimic", "onnx", "torchscript"]
CLIP_FORMATS: tuple[str, ...] = ("mjcf", "mjx", "dm_control", "urdf", "glb", "obj", "csv", "npz", "smpl", "amass",
                                 "beyondmimic")
POLICY_FORMATS: tuple[str, ...] = ("onnx", "torchscript")


@dataclass(frozen=True)
class ExportConfig:
    """crisp export: write a clip or a trained policy in the formats other stacks read.

    Attributes:
        source: a clip (registered name or directory) for clip formats; a training checkpoint
            (checkpoint.pt or its run directory) for onnx/torchscript.
        format: one or more formats; all is every clip format (all but onnx and torchscript).
        output: folder that receives one subfolder per kind of export.
        quat_order: quaternion order of the CSV and the fields npz (wxyz as MuJoCo, Isaac Lab;
            xyzw as Isaac Gym, PyBullet).
        smpl_up_axis: world up axis of the SMPL export (z as AMASS/PHC, y as SMPL's own).
        color_by_source: colour mesh primitives by source (planar blue, contact orange).
        keyframes: one MJCF <key> per motion frame in track.xml.
        overwrite: replace an existing output folder (it is written whole beside it and
            swapped in, so an interrupted export leaves the previous one as it was).
    """

    source: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="SOURCE")]
    format: tuple[Format, ...] = ("mjcf",)
    output: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("export")
    quat_order: Literal["wxyz", "xyzw"] = "wxyz"
    smpl_up_axis: Literal["z", "y"] = "z"
    color_by_source: bool = False
    keyframes: bool = True
    overwrite: bool = False

    def formats(self) -> tuple[str, ...]:
        """The requested formats, ``all`` expanded, duplicates dropped, in a stable order."""
        wanted = set(CLIP_FORMATS) if "all" in self.format else set(self.format)
        unknown = wanted - set(CLIP_FORMATS) - set(POLICY_FORMATS)
        if unknown or not wanted:
            raise ValueError(f"format must name some of {('all', *CLIP_FORMATS, *POLICY_FORMATS)}, got {self.format}")
        if wanted & set(POLICY_FORMATS) and wanted & set(CLIP_FORMATS):
            raise ValueError("policy formats (onnx, torchscript) take a checkpoint and clip formats a clip; "
                             "export them in separate calls")
        return tuple(f for f in (*CLIP_FORMATS, *POLICY_FORMATS) if f in wanted)


def export_clip(clip: Clip, output: str | Path, formats: tuple[str, ...], config: ExportConfig | None = None
                ) -> list[Path]:
    """Write ``clip`` in each of ``formats`` (:data:`CLIP_FORMATS`) under ``output``; returns the files."""
    config = config or ExportConfig(source=str(clip.path))
    unknown = set(formats) - set(CLIP_FORMATS)
    if unknown:
        raise ValueError(f"clip formats are {CLIP_FORMATS}, got {sorted(unknown)}")
    kind = getattr(clip, "scene_kind", "boxes")
    if kind != "boxes":
        raise ValueError(f"clip {clip.name!r} has a {kind!r} scene; export takes box scenes (scene_kind 'boxes')")
    output = Path(output)
    mjcf_config = MjcfExportConfig(keyframes=config.keyframes)
    written: list[Path] = []
    for fmt in tqdm(formats, desc="export", unit="format", disable=len(formats) < 2):
        if fmt in ("mjcf", "mjx", "dm_control"):
            written += write_mjcf(clip, output / fmt, "mujoco" if fmt == "mjcf" else fmt, mjcf_config)
        elif fmt == "urdf":
            written += write_urdf(clip.boxes, output / "urdf", UrdfConfig())
        elif fmt in ("glb", "obj"):
            written.append(write_scene_mesh(clip.boxes, output / "mesh" / f"scene.{fmt}", config.color_by_source))
        elif fmt == "csv":
            written.append(write_motion_csv(clip.motion, output / "motion" / "motion.csv", config.quat_order))
        elif fmt == "npz":
            written += [write_motion_npz(clip.motion, output / "motion" / f"motion_{layout}.npz", layout,
                                         config.quat_order) for layout in ("fields", "qpos")]
        elif fmt == "smpl":
            written.append(write_motion_npz(clip.motion, output / "motion" / "motion_smpl.npz", "smpl",
                                            up_axis=config.smpl_up_axis))
        else:  # amass, beyondmimic
            written.append(write_motion_npz(clip.motion, output / "motion" / f"motion_{fmt}.npz", fmt))
    return written


def export(config: ExportConfig) -> list[Path]:
    """Run ``crisp export`` for ``config``; returns the files written.

    The whole output folder is built beside ``config.output`` and renamed into place: an
    interrupted export never leaves a folder mixing two exports, and an existing folder is
    kept unless ``config.overwrite``.
    """
    formats = config.formats()
    output = Path(config.output)
    clip = None if set(formats) <= set(POLICY_FORMATS) else load_clip(config.source)  # fail before writing
    with atomic_directory(output, config.overwrite) as tmp:  # refuses an existing output first
        if clip is None:
            from crisp_gym.export.policy import export_checkpoint  # torch only when a policy is exported

            written = export_checkpoint(config.source, tmp / "policy", formats)
        else:
            written = export_clip(clip, tmp, formats, config)
    return [output / Path(f).relative_to(tmp) for f in written]


def main(argv: list[str] | None = None) -> int:
    """``crisp export SOURCE --format F [F ...] -o OUT`` (see :class:`ExportConfig`)."""
    config = tyro.cli(ExportConfig, args=argv, prog="crisp export")
    for path in export(config):
        print(path)
    return 0
