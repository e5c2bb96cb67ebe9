"""Synthetic depth videos and alignment: render speed, and alignment accuracy on the benchmark suite.

Speed (one run, same poses): :func:`crisp_gym.synth.video.render_synth_video` for a
``--speed-frames`` video at ``--size`` (depth, RGB, masks and the whole noise model, with the
time per stage), and its ray casting against the baseline of ray-casting the same frames with
:class:`crisp_gym.reconstruct.raycast.DepthRenderer` (depth and ids only).

Accuracy: every case of :func:`crisp_gym.synth.video.benchmark_suite` (default noise: unknown
scale, drift, distortion, per-pixel noise, flying pixels) is aligned from its camera-frame
motion; the table gives the scale error, the gravity error and the floor's height error under
the person's path (:func:`crisp_gym.synth.truth.alignment_errors`).

    python benchmarks/synth_align.py --seeds 10 --size 512x384
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import tyro
from tqdm import tqdm

from crisp_gym.reconstruct.align import align
from crisp_gym.reconstruct.body_mesh import BodyMesher
from crisp_gym.reconstruct.io import MotionInput
from crisp_gym.reconstruct.raycast import DepthRenderer, box_mesh
from crisp_gym.synth.truth import alignment_errors
from crisp_gym.synth.video import (  # fmt: skip
    SynthSpec,
    SynthVideoConfig,
    benchmark_suite,
    occluded_suite,
    render_synth_video,
)


@dataclass(frozen=True)
class Args:
    seeds: int = 10
    """Cases of the benchmark suite."""
    size: str = "512x384"
    """Image size WIDTHxHEIGHT."""
    speed_frames: int = 300
    """Frames of the timed render."""
    occluded: bool = True
    """Also align the occluded-support suite (6 cases)."""


def speed(width: int, height: int, frames: int) -> dict[str, float]:
    """Seconds for our full render and for the per-frame DepthRenderer baseline, same poses."""
    spec = benchmark_suite([0])[0]
    start = time.perf_counter()
    video = render_synth_video(spec, SynthVideoConfig(width=width, height=height, frames=frames), progress=False)
    ours = time.perf_counter() - start
    mesher = BodyMesher()
    renderer = DepthRenderer([box_mesh(b) for b in video.boxes])
    qpos = video.motion.qpos()
    start = time.perf_counter()
    for t in range(frames):
        renderer.render(video.frames.intrinsic, video.cam_c2w[t], width, height, dynamic=[mesher.trimesh(qpos[t])])
    baseline = time.perf_counter() - start
    raycast = video.meta["render_seconds_by_stage"]["raycast"]
    return {"frames": frames, "ours_s": ours, "ours_render_loop_s": video.meta["render_seconds"],
            **{f"ours_{k}_s": v for k, v in video.meta["render_seconds_by_stage"].items()},
            "baseline_depth_only_s": baseline, "baseline_over_ours_raycast": baseline / raycast}


def accuracy(spec: SynthSpec, width: int, height: int) -> dict:
    video = render_synth_video(spec, SynthVideoConfig(width=width, height=height), progress=False)
    start = time.perf_counter()
    result = align(video.frames, MotionInput(video.motion_camera, "camera"))
    seconds = time.perf_counter() - start
    errors = alignment_errors(result.alignment.scale, result.alignment.world_from_input, video)
    return {"case": spec.name, "frames": video.frames.num_frames, "true_scale": video.scale,
            "align_s": seconds, **errors, "feet_height_m": result.alignment.diagnostics["feet_height_m"]}


def _table(rows: list[dict]) -> str:
    if not rows:
        return "(no cases)"
    header = ("| case | frames | true scale | scale error | gravity error (deg) | floor error (cm, mean / max) "
              "| feet height (cm) | align (s) |")
    lines = [header, "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['frames']} | {r['true_scale']:.3f} | {100 * r['scale_error']:+.2f} % "
                     f"| {r['gravity_error_deg']:.2f} | {100 * r['floor_error_m']:.1f} / "
                     f"{100 * r['floor_error_max_m']:.1f} | {100 * r['feet_height_m']:+.1f} | {r['align_s']:.1f} |")
    scale = np.abs([r["scale_error"] for r in rows])
    gravity = np.array([r["gravity_error_deg"] for r in rows])
    floor = np.array([r["floor_error_m"] for r in rows])
    lines.append(f"| **median / max** | | | {100 * np.median(scale):.2f} / {100 * scale.max():.2f} % "
                 f"| {np.median(gravity):.2f} / {gravity.max():.2f} | {100 * np.median(floor):.1f} / "
                 f"{100 * floor.max():.1f} | | |")
    return "\n".join(lines)


def main(args: Args) -> None:
    width, height = (int(x) for x in args.size.split("x"))
    timing = speed(width, height, args.speed_frames)
    print(f"render {timing['frames']} frames {width}x{height}: ours {timing['ours_s']:.1f} s in all, "
          f"{timing['ours_render_loop_s']:.1f} s render loop (ray casting {timing['ours_raycast_s']:.1f} s, "
          f"noise {timing['ours_noise_s']:.1f} s, shading {timing['ours_shading_s']:.1f} s); baseline "
          f"DepthRenderer ray casting: {timing['baseline_depth_only_s']:.1f} s; baseline / ours (ray casting) = "
          f"{timing['baseline_over_ours_raycast']:.2f}")
    rows = [accuracy(spec, width, height) for spec in tqdm(benchmark_suite(range(args.seeds)), desc="suite")]
    print("\nbenchmark suite\n" + _table(rows))
    if args.occluded:
        rows = [accuracy(spec, width, height) for spec in tqdm(occluded_suite(), desc="occluded")]
        print("\noccluded-support suite\n" + _table(rows))


if __name__ == "__main__":
    main(tyro.cli(Args))
