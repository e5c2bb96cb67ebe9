"""A motion library: several clips composed into one MuJoCo model, so one batch steps them all.

Every clip keeps its own scene, but all scenes live in one model, each shifted along x to its
own region (``gap`` metres of empty space between the regions' extents, far beyond anything a
body or an observed scene point can reach). A simulation tracking clip ``c`` is placed in
clip ``c``'s region: its reference, its scene and its scene samples carry the same offset.
Every observation is relative to the pelvis (positions) or its height above z = 0 (the
offsets are horizontal), so a simulation sees exactly what the single-clip env shows it.

The references of all clips are stored end to end in one :class:`~crisp_gym.envs.tracking.Reference`;
:meth:`MotionLibrary.global_frames` maps (clip, frame of that clip) to its rows.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from crisp_gym.clip import Clip
from crisp_gym.envs import tracking
from crisp_gym.envs.config import TrackConfig
from crisp_gym.mjcf_scene import scene_surface
from crisp_gym.motion import humanoid_body_ids, humanoid_qpos_adr
from crisp_gym.registry import load_clip, resolve_clip_names
from crisp_gym.scene import Box

ClipSource = str | os.PathLike | Clip
"""A clip name, a registry tag (``"bundled"``, ``"stairs"``...), a clip directory or a loaded clip."""

REGION_GAP = 20.0
"""Metres of empty space between two clips' regions (scene extent and pelvis path)."""


def load_clips(clips: ClipSource | Sequence[ClipSource]) -> list[Clip]:
    """Clips named by ``clips``: one source or a list; a registry tag expands to its clips.

    The same clip may not appear twice (weight it instead, with ``clip_weights``).
    """
    sources = [clips] if isinstance(clips, (str, os.PathLike, Clip)) else list(clips)
    if not sources:
        raise ValueError("clip must name at least one clip")
    loaded: list[Clip] = []
    for source in sources:
        if isinstance(source, Clip):
            loaded.append(source)
        else:
            loaded.extend(load_clip(name) for name in resolve_clip_names(source))
    paths = [c.path.resolve() for c in loaded]
    if len(set(paths)) != len(paths):
        raise ValueError(f"a clip appears more than once in {[c.name for c in loaded]}")
    return loaded


@dataclass(frozen=True)
class ClipRegion:
    """Where one clip lives in the library.

    Attributes:
        offset: (3,) horizontal shift of the clip's scene and reference in the composed model.
        first: row of the clip's frame 0 in the library's reference.
        num_frames: the clip's frames at the control rate.
    """

    offset: np.ndarray
    first: int
    num_frames: int


def _extent(clip: Clip, path: np.ndarray) -> tuple[float, float]:
    """(min x, max x) of a clip's scene and pelvis path."""
    if clip.scene_kind == "boxes":
        xs = np.concatenate([b.corners()[:, 0] for b in clip.boxes] + [path[:, 0]])
    else:
        xs = np.concatenate([scene_surface(clip.scene_xml).vertices[:, 0], path[:, 0]])
    return float(xs.min()), float(xs.max())


def _placed(box: Box, offset: np.ndarray, clip_index: int | None) -> Box:
    """``box`` at its clip's offset; in a library of several clips its name gets the clip's index
    (every clip may have a box called "floor")."""
    box = box.translated(offset)
    return box if clip_index is None or not box.name else replace(box, name=f"clip{clip_index}/{box.name}")


def layout_offsets(extents: Sequence[tuple[float, float]], gap: float = REGION_GAP) -> np.ndarray:
    """(C, 3) offsets along x placing each extent ``gap`` beyond the previous one; the first stays put."""
    offsets = np.zeros((len(extents), 3))
    for i in range(1, len(extents)):
        previous_end = extents[i - 1][1] + offsets[i - 1, 0]
        offsets[i, 0] = previous_end + gap - extents[i][0]
    return offsets


class MotionLibrary:
    """Clips composed into one model, with their references end to end.

    Args:
        clips: what :func:`load_clips` accepts.
        config: the env config (rates, scene-aware sampling).

    Attributes:
        clips: the loaded clips, in library order.
        names: their names.
        regions: one :class:`ClipRegion` per clip.
        model: the humanoid with every clip's scene at its offset.
        reference: all clips' references, shifted by their offsets, end to end.
        body_ids: the humanoid's 24 body ids in ``model``.
        point_trees: per clip, a KD-tree over its scene samples (scene-aware only, else ``None``).
    """

    def __init__(self, clips: ClipSource | Sequence[ClipSource], config: TrackConfig):
        self.clips = load_clips(clips)
        self.names = [c.name for c in self.clips]
        timestep = 1.0 / config.sim_hz
        humanoid = tracking.build_track_model([], timestep)  # the kinematics need only the humanoid
        references = [tracking.Reference.from_motion(c.motion, humanoid, config.control_hz) for c in self.clips]
        if len(self.clips) == 1:
            offsets = np.zeros((1, 3))
        else:
            offsets = layout_offsets([_extent(c, r.body_pos[:, 0]) for c, r in zip(self.clips, references)])
        firsts = np.concatenate([[0], np.cumsum([r.num_frames for r in references])[:-1]])
        self.regions = [ClipRegion(offset=o, first=int(f), num_frames=r.num_frames)
                        for o, f, r in zip(offsets, firsts, references)]
        boxes = [_placed(box, o, i if len(self.clips) > 1 else None)
                 for i, (c, o) in enumerate(zip(self.clips, offsets)) for box in c.boxes]
        self.model = tracking.build_track_model(
            boxes, timestep=timestep,
            scene_xmls=[(c.scene_xml, o) for c, o in zip(self.clips, offsets) if c.scene_kind != "boxes"])
        if humanoid_qpos_adr(self.model) != 0:
            raise ValueError("the humanoid's free joint must come first in the composed model")
        self.body_ids = humanoid_body_ids(self.model)
        self.reference = tracking.Reference.concatenate([r.translated(o) for r, o in zip(references, offsets)])
        self._first = firsts.astype(int)
        self._length = np.array([r.num_frames for r in references])
        self.point_trees = None
        if config.scene_aware:
            self.point_trees = [cKDTree(self._scene_points(c, r, o, config))
                                for c, r, o in zip(self.clips, references, offsets)]

    @staticmethod
    def _scene_points(clip: Clip, reference: tracking.Reference, offset: np.ndarray,
                      config: TrackConfig) -> np.ndarray:
        points = (tracking.scene_samples(clip.boxes, reference, config) if clip.scene_kind == "boxes"
                  else tracking.mesh_scene_samples(scene_surface(clip.scene_xml), reference, config))
        if len(points) == 0:
            raise ValueError(f"scene_aware=True but the scene of clip {clip.name!r} has no surface within "
                             f"point_radius of the motion")
        return points + offset

    @property
    def num_clips(self) -> int:
        return len(self.clips)

    @property
    def num_frames(self) -> np.ndarray:
        """(C,) frames of each clip at the control rate."""
        return self._length

    def global_frames(self, clip_ids: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Rows of :attr:`reference` for frame ``frames`` of clips ``clip_ids``."""
        return self._first[clip_ids] + frames

    def last_frames(self, clip_ids: np.ndarray) -> np.ndarray:
        """Rows of :attr:`reference` holding the last frame of clips ``clip_ids``."""
        return self._first[clip_ids] + self._length[clip_ids] - 1
