"""Clip directories: a scene and a motion that belong together.

A clip directory holds ``scene.xml`` (MJCF of the static scene: the boxes of
``primitives.json``, or for the TSDF baselines a heightfield or meshes, see ``scene_kind``),
``motion.npz``, ``primitives.json`` and ``meta.json`` (provenance, fps, scale, timings, counts). :func:`write_clip` builds the
directory under a temporary name and renames it into place, so an interrupted run never
leaves a half-written clip.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from crisp_gym.atomic import atomic_directory
from crisp_gym.file_errors import reading
from crisp_gym.motion import Motion, check_plausible
from crisp_gym.scene import Box, load_primitives, save_primitives, write_scene_xml

CLIP_FILES = ("scene.xml", "motion.npz", "primitives.json", "meta.json")
SCENE_KINDS = ("boxes", "heightfield", "convex_pieces", "dense_mesh")
"""``meta.json["scene_kind"]``: what ``scene.xml`` holds (absent means ``"boxes"``). Only box
scenes have primitives; the others (``crisp_gym.reconstruct.baselines``) bring their geometry in
``scene.xml`` and the files it references, inside the clip directory."""


@dataclass(frozen=True)
class Clip:
    """A loaded clip.

    Attributes:
        path: the clip directory.
        boxes: the scene's primitives.
        motion: the reference motion, in the scene's frame.
        meta: the contents of ``meta.json``.
    """

    path: Path
    boxes: list[Box]
    motion: Motion
    meta: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return str(self.meta.get("name", self.path.name))

    @property
    def scene_xml(self) -> Path:
        return self.path / "scene.xml"

    @property
    def scene_kind(self) -> str:
        """One of :data:`SCENE_KINDS`; ``"boxes"`` for clips whose meta does not say."""
        return str(self.meta.get("scene_kind", "boxes"))


def write_clip(directory: str | Path, boxes: list[Box], motion: Motion, meta: dict | None = None,
               overwrite: bool = False, write_scene: Callable[[Path], None] | None = None,
               write_extras: Callable[[Path], None] | None = None) -> Path:
    """Write a clip directory atomically and return its path.

    ``meta`` is completed with the motion's ``fps``, ``num_frames`` and the primitive counts.
    ``write_scene``, for scenes that are not boxes, writes ``scene.xml`` and the files it
    references into the directory being built (its argument) instead of the boxes' scene.
    ``write_extras`` writes further files (a report page, a video) into it, so they appear with
    the clip or not at all.
    """
    directory = Path(directory)
    meta = dict(meta or {})
    meta.setdefault("name", directory.name)
    meta.update(fps=motion.fps, num_frames=motion.num_frames,
                num_primitives=len(boxes),
                num_contact_primitives=sum(b.source == "contact" for b in boxes))
    with atomic_directory(directory, overwrite) as tmp:
        if write_scene is None:
            write_scene_xml(boxes, tmp / "scene.xml")
        else:
            write_scene(tmp)
        motion.save(tmp / "motion.npz")
        save_primitives(boxes, tmp / "primitives.json")
        (tmp / "meta.json").write_text(json.dumps(meta, indent=1, sort_keys=True))
        if write_extras is not None:
            write_extras(tmp)
    return directory


def load_clip_dir(directory: str | Path) -> Clip:
    """Load a clip directory, checking that every file is there."""
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"no clip directory at {directory}")
    missing = [f for f in CLIP_FILES if not (directory / f).is_file()]
    if missing:
        raise FileNotFoundError(f"{directory} is not a complete clip: missing {missing} "
                                f"(a clip holds {list(CLIP_FILES)})")
    try:
        meta = json.loads((directory / "meta.json").read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{directory / 'meta.json'} is not valid JSON: {err}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{directory / 'meta.json'} must hold a JSON object, got {type(meta).__name__}")
    if meta.get("scene_kind", "boxes") not in SCENE_KINDS:
        raise ValueError(f"{directory}/meta.json: scene_kind must be one of {SCENE_KINDS}, got {meta['scene_kind']!r}")
    motion = Motion.load(directory / "motion.npz")
    try:
        check_plausible(motion)  # a clip is simulated, exported and trained on: refuse what no body can do
    except ValueError as err:
        raise ValueError(f"{directory / 'motion.npz'}: {err}") from None
    with reading(directory / "primitives.json", "primitives file"):
        boxes = load_primitives(directory / "primitives.json")
    return Clip(path=directory, boxes=boxes, motion=motion, meta=meta)
