"""``crisp synth``: render a synthetic depth video with ground truth into a folder."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from crisp_gym.synth.camera import CameraConfig
from crisp_gym.synth.depth_noise import DepthNoise
from crisp_gym.synth.truth import write_synth_input
from crisp_gym.synth.video import SynthSpec, SynthVideoConfig, render_synth_video


@dataclass(frozen=True)
class SynthArgs:
    """Render a synthetic depth video of a person in a box scene, with its ground truth."""

    output: Annotated[Path, tyro.conf.arg(aliases=["-o"])]
    """Directory to write (input.npz, motion_camera.npz, gt/)."""
    kind: Literal["flat_walk", "stairs_up", "stairs_down", "platform_step", "chair_sit", "random"] = "random"
    """Scene kind (random: stairs, a platform or a seat with background boxes)."""
    seed: int = 0
    """Seed of the scene, motion, camera and noise."""
    view: Literal["orbit", "low", "upper_body"] = "orbit"
    """Camera view: orbit, low (raised tops never visible), upper_body (supports off-frame)."""
    frames: int | None = None
    """Number of frames (default: the motion's length)."""
    size: str = "512x384"
    """Image size WIDTHxHEIGHT."""
    distractors: int = 0
    """Background boxes (a wall and blocks) beside the path."""
    clip: str | None = None
    """Render this registered clip (name or directory) instead of generating a scene."""
    clean: bool = False
    """Exact metric depth (no scale, drift, distortion, noise, flying pixels or holes)."""
    noise: DepthNoise = field(default_factory=DepthNoise)
    camera: CameraConfig = field(default_factory=CameraConfig)
    overwrite: bool = False
    """Replace an existing output directory."""


def _parse_size(size: str) -> tuple[int, int]:
    try:
        width, height = (int(x) for x in size.lower().split("x"))
    except ValueError:
        raise ValueError(f"size must be WIDTHxHEIGHT (e.g. 512x384), got {size!r}") from None
    return width, height


def main(argv: list[str] | None = None) -> int:
    """``crisp synth``: render and write a synthetic input."""
    args = tyro.cli(SynthArgs, args=argv, prog="crisp synth")
    width, height = _parse_size(args.size)
    config = SynthVideoConfig(width=width, height=height, frames=args.frames,
                              noise=DepthNoise.clean() if args.clean else args.noise, camera=args.camera)
    spec = SynthSpec(args.kind, args.seed, args.view, args.distractors, args.clip)
    if args.output.exists() and not args.overwrite:
        raise FileExistsError(f"{args.output} exists; pass --overwrite to replace it")
    video = render_synth_video(spec, config)
    out = write_synth_input(args.output, video, overwrite=args.overwrite)
    hidden = [b["name"] for b in video.meta["boxes"] if b["top_visible_pixels"] == 0]
    print(f"wrote {spec.name}: {video.frames.num_frames} frames {width}x{height} in "
          f"{video.meta['render_seconds']:.1f} s, scale {video.scale:.3f}, boxes never seen from above: "
          f"{hidden or 'none'} -> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
