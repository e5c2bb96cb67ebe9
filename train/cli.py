"""``crisp train``: a profile's defaults, every :class:`~crisp_gym.train.config.TrainConfig` field a flag."""

from __future__ import annotations

import argparse
import glob
import os
import sys

import tyro

from crisp_gym.train.config import PROFILES, TrainConfig


def cuda_available() -> bool:
    """Whether torch sees a CUDA device. Without an NVIDIA device node (``/dev/nvidia0``, or WSL's
    ``/dev/dxg``) Linux has none, and importing torch only to be told so costs seconds that
    ``--help`` and a mistyped flag would wait for."""
    if sys.platform == "linux" and not (glob.glob("/dev/nvidia[0-9]*") or os.path.exists("/dev/dxg")):
        return False
    import torch

    return torch.cuda.is_available()


def main(argv: list[str] | None = None) -> int:
    """``crisp train``: ``--profile {auto,paper,cpu}`` picks the defaults, every other flag
    is a :class:`TrainConfig` field (``--clip NAME --scene-aware --frames N --num-envs N -o RUN
    --resume``...). ``auto`` is ``paper`` when CUDA is available, else ``cpu``."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--profile", choices=("auto", *PROFILES), default="auto")
    known, rest = pre.parse_known_args(argv)
    profile = known.profile
    if profile == "auto":
        profile = "paper" if cuda_available() else "cpu"
    cfg = tyro.cli(TrainConfig, args=rest, default=PROFILES[profile](), prog="crisp train",
                   description=f"Train a tracking policy with PPO (defaults: the {profile!r} profile; "
                               f"--profile {{auto,paper,cpu}} picks another).")
    # Imported once the flags parse: TorchRL and tensordict take seconds to import, which
    # `--help` and a mistyped flag should not wait for.
    from crisp_gym.train.ppo import train

    result = train(cfg)
    print(f"{result.iteration} iterations, {result.frames} frames; checkpoint: {result.checkpoint}")
    return 130 if result.interrupted else 0


if __name__ == "__main__":
    raise SystemExit(main())
