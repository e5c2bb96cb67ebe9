"""Simulation speed on a clip's planar boxes against TSDF baselines of the same scene.

The clip's box scene is rendered into depth from cameras walking along both sides of the
motion's path, fused into a TSDF mesh and turned into a heightfield and convex pieces
(``crisp_gym.reconstruct.baselines``), and, as an unfaithful reference, the raw mesh as one geom. The
same reference motion is then tracked in the batched ``CrispTrack-v0`` on each scene: PD toward
the reference (zero residual actions), reference state init on every reset, so all scenes do the
same work. Scenes are measured in interleaved rounds so load changes hit them alike; the table
gives the median env-steps/s and the box scene's speed as a multiple of each.

    python benchmarks/scene_fps.py --clip stairs_up --num-envs 64 --threads 2 --seconds 3 --rounds 3

The paper reports 23K FPS on its planar primitives against 16K on a dense mesh (1.43x).
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

import crisp_gym  # noqa: F401  (registers CrispTrack-v0)
from crisp_gym.clip import Clip
from crisp_gym.envs.track_vector import CrispTrackVectorEnv
from crisp_gym.geometry import intrinsic_from_fov, look_at
from crisp_gym.reconstruct.baselines import ColliderConfig, TsdfConfig, write_baseline_clips
from crisp_gym.reconstruct.frames import Frames
from crisp_gym.reconstruct.raycast import DepthRenderer, box_mesh
from crisp_gym.registry import load_clip


@dataclass(frozen=True)
class Args:
    clip: str = "stairs_up"
    """Registered clip name or clip directory (a box scene)."""
    num_envs: int = 64
    threads: int = 2
    seconds: float = 3.0
    """Measured seconds per scene per round."""
    rounds: int = 3
    voxel_size: float = 0.02
    """TSDF voxel (m); the heightfield and the pieces keep their defaults."""
    camera_spacing: float = 0.4
    """Distance (m) between camera stations along the path (one camera on each side)."""
    width: int = 320
    height: int = 240
    dense_mesh: bool = True
    """Also time the raw mesh as one geom (collides as its convex hull: not a faithful scene)."""
    out: Path | None = None
    """Where the baseline clips are written (default: a temporary folder)."""
    seed: int = 0


def _unit(v: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(norm > 1e-9, v / np.maximum(norm, 1e-9), [1.0, 0.0])


def path_frames(clip: Clip, args: Args) -> Frames:
    """Depth of the clip's boxes from cameras 2.5 m either side of the pelvis path (and 1 m
    beyond its ends), 1.8 m up, looking down at the path just ahead."""
    path = clip.motion.root_pos[:, :2]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    stations = np.arange(-1.0, arc[-1] + 1.0 + 1e-9, args.camera_spacing)
    centre = np.stack([np.interp(stations, arc, path[:, k]) for k in range(2)], axis=1)  # clamped at the ends
    ends = _unit(np.stack([path[min(5, len(path) - 1)] - path[0], path[-1] - path[max(len(path) - 6, 0)]]))
    centre += np.minimum(stations, 0)[:, None] * ends[0] + np.maximum(stations - arc[-1], 0)[:, None] * ends[1]
    heading = _unit(np.gradient(centre, axis=0)) if len(centre) > 1 else np.array([[1.0, 0.0]])
    side = np.stack([-heading[:, 1], heading[:, 0]], axis=1)
    poses = [look_at(np.r_[c + sign * 2.5 * n, 1.8], np.r_[c + 0.3 * h, 0.0])
             for c, h, n in zip(centre, heading, side) for sign in (-1.0, 1.0)]
    intrinsic = intrinsic_from_fov(args.width, args.height, 70.0)
    renderer = DepthRenderer([box_mesh(b) for b in clip.boxes])
    depth = np.stack([renderer.render(intrinsic, pose, args.width, args.height)[0] for pose in poses])
    return Frames(depth=depth, intrinsic=intrinsic, cam_c2w=np.stack(poses), fps=clip.motion.fps)


def measure(venv: CrispTrackVectorEnv, seconds: float) -> tuple[float, int, int, float]:
    """(env-steps/s, env-steps, episode ends, mean contacts per simulation) of zero-residual PD
    tracking over ``seconds``."""
    zero = np.zeros((venv.num_envs, venv.model.nu))
    ncon = venv.batch.bind("ncon")
    for _ in range(3):
        venv.step(zero)
    steps, ends, contacts, start = 0, 0, 0.0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        _, _, terminated, truncated, _ = venv.step(zero)
        steps += venv.num_envs
        ends += int(np.sum(terminated | truncated))
        contacts += float(np.sum(ncon[:]))
    return steps / (time.perf_counter() - start), steps, ends, contacts / steps


def main(args: Args) -> dict[str, dict]:
    clip = load_clip(args.clip)
    if clip.scene_kind != "boxes":
        raise ValueError(f"--clip must be a box scene, got scene_kind {clip.scene_kind!r}")
    with tempfile.TemporaryDirectory(prefix="scene_fps_") as tmp:
        return run(clip, args, args.out or Path(tmp))


def run(clip: Clip, args: Args, out: Path) -> dict[str, dict]:
    """Write the baselines of ``clip`` into ``out``, time all scenes, print the table."""
    frames = path_frames(clip, args)
    kinds = ("heightfield", "convex_pieces", "dense_mesh") if args.dense_mesh else ("heightfield", "convex_pieces")
    written = write_baseline_clips(out, frames, clip.motion, clip.name, kinds=kinds,
                                   tsdf=TsdfConfig(voxel_size=args.voxel_size), colliders=ColliderConfig(),
                                   overwrite=True)
    scenes = {"boxes": clip.path, **written}
    venvs = {name: CrispTrackVectorEnv(args.num_envs, clip=str(path), num_threads=args.threads)
             for name, path in scenes.items()}
    for venv in venvs.values():
        venv.reset(seed=args.seed)
    rates: dict[str, list[float]] = {name: [] for name in scenes}
    totals = {name: np.zeros(3) for name in scenes}  # env-steps, episode ends, contacts
    for _ in range(args.rounds):
        for name, venv in venvs.items():
            rate, steps, ends, contacts = measure(venv, args.seconds)
            rates[name].append(rate)
            totals[name] += [steps, ends, contacts * steps]
    for venv in venvs.values():
        venv.close()
    results = {}
    for name, path in scenes.items():
        meta = json.loads((Path(path) / "meta.json").read_text())
        steps, ends, contacts = totals[name]
        results[name] = {
            "scene_geoms": int(np.sum(venvs[name].model.geom_bodyid == 0)),
            "num_primitives": meta.get("num_primitives"),
            "num_pieces": meta.get("num_pieces"),
            "num_triangles": meta.get("num_triangles"),
            "hfield": f"{meta['hfield_rows']}x{meta['hfield_cols']}" if "hfield_rows" in meta else None,
            "env_steps_per_s": float(np.median(rates[name])),
            # Ratio within each round (same load), then the median over rounds.
            "box_speedup": float(np.median(np.divide(rates["boxes"], rates[name]))),
            "episode_ends_per_1k_steps": 1000.0 * ends / steps,
            "contacts_per_sim": contacts / steps,
            "convert_s": meta.get("timings", {}).get("convert_s"),
        }
    tsdf_meta = json.loads((Path(written["heightfield"]) / "meta.json").read_text())
    print(f"\n'{clip.name}': {frames.num_frames} depth frames {args.width}x{args.height}, TSDF voxel "
          f"{args.voxel_size} m -> {tsdf_meta['dense_triangles']:,} triangles in "
          f"{tsdf_meta['timings']['tsdf_s']:.1f} s; {args.num_envs} envs, {args.threads} threads, "
          f"{args.rounds} rounds x {args.seconds} s\n")
    print("| scene | geoms | size | env-steps/s | boxes ÷ this | contacts / sim | episode ends / 1k steps "
          "| conversion (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, r in results.items():
        size = (f"{r['num_primitives']} boxes" if name == "boxes" else f"{r['hfield']} grid" if r["hfield"]
                else f"{r['num_pieces']} pieces, {r['num_triangles']:,} tri" if r["num_pieces"]
                else f"{r['num_triangles']:,} tri")
        convert = "" if r["convert_s"] is None else f"{r['convert_s']:.1f}"
        print(f"| {name} | {r['scene_geoms']} | {size} | {r['env_steps_per_s']:,.0f} | {r['box_speedup']:.2f} | "
              f"{r['contacts_per_sim']:.1f} | {r['episode_ends_per_1k_steps']:.1f} | {convert} |")
    return results


if __name__ == "__main__":
    main(tyro.cli(Args))
