"""``crisp view CLIP_OR_RUN``: an interactive 3D viewer in the browser (viser).

    crisp view stairs_up                        # the clip: its primitives and reference motion
    crisp view runs/flat_walk --clip flat_walk  # and a policy rollout from frame 0 beside it
    crisp view runs/clips/my_video --points     # and the input's point cloud, when the clip has one

It serves ``http://localhost:8080`` (``--port``): the primitives coloured by source (planar blue,
contact orange), the reference humanoid (translucent green), the policy's simulated humanoid
(when a policy is given), the input point cloud (``--points``), and a timeline: a frame slider
and a play button. Ctrl-C stops it.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import mujoco
import numpy as np
import trimesh
import tyro

from crisp_gym.clip import Clip
from crisp_gym.humanoid import BODY_NAMES, build_humanoid
from crisp_gym.motion import compute_kinematics, humanoid_body_ids
from crisp_gym.registry import load_clip
from crisp_gym.scene import Box

SOURCE_RGB = {"planar": (115, 153, 217), "contact": (230, 140, 77)}
REFERENCE_RGB, SIMULATED_RGB = (80, 220, 110), (230, 160, 120)


@dataclass(frozen=True)
class ViewArgs:
    """Show a clip (or a run's policy on it) in an interactive 3D viewer in the browser."""

    source: tyro.conf.Positional[str]
    """A clip (registered name or directory), or a run directory / policy file."""
    clip: str | None = None
    """With a run or policy: the clip to roll it out on (default: its first training clip)."""
    points: bool = False
    """Also show the point cloud of the clip's input (meta.json → input), when it can be read."""
    max_points: int = 200_000
    """Points shown at most (a random subset)."""
    port: Annotated[int, tyro.conf.arg(aliases=("-p",))] = 8080
    """Port of the viewer's web page."""


@dataclass(frozen=True)
class Track:
    """A humanoid's world body poses over the clip: (T, 24, 3) positions, (T, 24, 4) w x y z."""

    body_pos: np.ndarray
    body_quat: np.ndarray


def body_meshes(model: mujoco.MjModel) -> dict[str, trimesh.Trimesh]:
    """Each humanoid body's collision geometry as one mesh in the body's frame."""
    ids = humanoid_body_ids(model)
    meshes = {}
    for name, body in zip(BODY_NAMES, ids):
        parts = []
        for g in np.flatnonzero(model.geom_bodyid == body):
            size, kind = model.geom_size[g], model.geom_type[g]
            if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
                part = trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=(8, 8))
            elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
                part = trimesh.creation.icosphere(subdivisions=2, radius=size[0])
            elif kind == mujoco.mjtGeom.mjGEOM_BOX:
                part = trimesh.creation.box(extents=2 * size)
            else:
                continue
            pose = np.eye(4)
            rotation = np.zeros(9)
            mujoco.mju_quat2Mat(rotation, model.geom_quat[g])
            pose[:3, :3], pose[:3, 3] = rotation.reshape(3, 3), model.geom_pos[g]
            parts.append(part.apply_transform(pose))
        if parts:
            meshes[name] = trimesh.util.concatenate(parts)
    return meshes


def reference_track(clip: Clip) -> Track:
    """The clip's reference motion as body poses (forward kinematics on the default humanoid)."""
    kin = compute_kinematics(clip.motion, build_humanoid())
    return Track(kin.body_pos, kin.body_quat)


def policy_track(policy_source: str | Path, clip: str | Path) -> Track:
    """The policy's simulated humanoid from frame 0 of ``clip``, until the episode ends."""
    from crisp_gym.envs.track import CrispTrackEnv  # noqa: PLC0415
    from crisp_gym.policy.files import load_actor  # noqa: PLC0415
    from crisp_gym.train.rollouts import torch_policy  # noqa: PLC0415

    loaded = load_actor(policy_source)
    policy = torch_policy(loaded.actor, loaded.scene_aware)
    env = CrispTrackEnv(clip=str(clip), scene_aware=loaded.scene_aware)
    obs, _ = env.reset(seed=0, options={"start_frame": 0})
    ids = humanoid_body_ids(env.model)
    pos, quat = [env.data.xpos[ids].copy()], [env.data.xquat[ids].copy()]
    done = False
    while not done:
        obs, _, terminated, truncated, _ = env.step(policy({k: v[None] for k, v in obs.items()})[0])
        pos.append(env.data.xpos[ids].copy())
        quat.append(env.data.xquat[ids].copy())
        done = terminated or truncated
    env.close()
    return Track(np.array(pos), np.array(quat))


def input_points(clip: Clip, max_points: int, seed: int = 0) -> np.ndarray | None:
    """The clip's input depth as world points (the reconstruction's scale and alignment from
    ``meta.json``), subsampled; ``None`` when the clip has no readable input."""
    from crisp_gym.reconstruct.io import read_frames  # noqa: PLC0415

    meta = clip.meta
    alignment = meta.get("alignment", {})
    if "input" not in meta or "world_from_input" not in alignment or not Path(meta["input"]).exists():
        return None
    frames = read_frames(meta["input"], progress=False).scaled(float(meta.get("scale", 1.0)))
    frames = frames.transformed(np.array(alignment["world_from_input"]))
    points = np.concatenate([frames.world_points(t)[frames.valid[t]] for t in range(frames.num_frames)])
    rng = np.random.default_rng(seed)
    return points[rng.choice(len(points), size=min(max_points, len(points)), replace=False)]


class Viewer:
    """The scene in a viser server: primitives, humanoids per track, optional points, a timeline."""

    def __init__(self, server, boxes: list[Box], tracks: dict[str, tuple[Track, tuple[int, int, int], float]],
                 points: np.ndarray | None = None):
        self.server, self.tracks = server, tracks
        scene = server.scene
        scene.add_light_hemisphere("/sky")
        for i, box in enumerate(boxes):
            scene.add_box(f"/scene/{box.name or i}", color=SOURCE_RGB[box.source], dimensions=2 * box.half_size,
                          position=box.center, wxyz=box.quat)
        if points is not None:
            scene.add_point_cloud("/points", points, colors=(150, 150, 150), point_size=0.01)
        meshes = body_meshes(build_humanoid())
        self.frames = {}
        for name, (_, color, opacity) in tracks.items():
            for body, mesh in meshes.items():
                self.frames[name, body] = scene.add_frame(f"/{name}/{body}", show_axes=False)
                scene.add_mesh_simple(f"/{name}/{body}/geom", mesh.vertices, mesh.faces, color=color,
                                      opacity=opacity)
        pelvis = next(iter(tracks.values()))[0].body_pos[0, 0]
        server.initial_camera.look_at = pelvis
        server.initial_camera.position = pelvis + np.array([0.5, -4.0, 1.5])  # from the side, a little above
        length = max(len(track.body_pos) for track, _, _ in tracks.values())
        self.slider = server.gui.add_slider("frame", min=0, max=length - 1, step=1, initial_value=0)
        self.playing = server.gui.add_checkbox("play", initial_value=False)
        self.slider.on_update(lambda _: self.show(int(self.slider.value)))
        self.show(0)

    def show(self, frame: int) -> None:
        """Pose every humanoid at ``frame`` (a track that ended earlier keeps its last pose)."""
        for (name, body), handle in self.frames.items():
            track = self.tracks[name][0]
            k, b = min(frame, len(track.body_pos) - 1), BODY_NAMES.index(body)
            handle.position, handle.wxyz = track.body_pos[k, b], track.body_quat[k, b]

    def run(self, fps: float) -> None:
        """Advance the slider while ``play`` is on, until Ctrl-C."""
        while True:
            if self.playing.value:
                self.slider.value = (int(self.slider.value) + 1) % (int(self.slider.max) + 1)
            time.sleep(1.0 / fps)


def policy_and_clip(args: ViewArgs) -> tuple[Path | None, str]:
    """(policy source or None, clip) from the arguments."""
    source = Path(args.source)
    is_policy = source.suffix == ".pt" or (source.is_dir() and not (source / "motion.npz").is_file()
                                           and any((source / f).is_file() for f in ("policy.pt", "checkpoint.pt")))
    if not is_policy:
        return None, args.source
    if args.clip is not None:
        return source, args.clip
    config = source / "config.json" if source.is_dir() else None
    if config is not None and config.is_file():
        return source, json.loads(config.read_text())["clip"][0]
    from crisp_gym.train.checkpoints import load_policy  # noqa: PLC0415

    return source, load_policy(source)[1].clip[0]


def main(argv: list[str] | None = None) -> int:
    """``crisp view``: see :class:`ViewArgs`."""
    args = tyro.cli(ViewArgs, args=argv, prog="crisp view")
    try:
        import viser  # noqa: PLC0415 - the viewer's web server
    except ModuleNotFoundError:
        raise ModuleNotFoundError("crisp view needs viser: pip install 'crisp-gym[view]'") from None
    policy, clip_source = policy_and_clip(args)
    clip = load_clip(clip_source)
    tracks = {"reference": (reference_track(clip), REFERENCE_RGB, 0.45)}
    if policy is not None:
        tracks["policy"] = (policy_track(policy, clip.path), SIMULATED_RGB, 1.0)
    points = input_points(clip, args.max_points) if args.points else None
    if args.points and points is None:
        print(f"crisp view: {clip.name} has no depth input to show (--points needs a clip reconstructed from an npz or "
              "RGB-D folder whose meta.json names it and its alignment)")
    server = viser.ViserServer(port=args.port, verbose=False)
    viewer = Viewer(server, clip.boxes, tracks, points)
    print(f"crisp view: {clip.name} at http://localhost:{args.port} (Ctrl-C stops)")
    try:
        viewer.run(clip.motion.fps)
    except KeyboardInterrupt:
        server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
