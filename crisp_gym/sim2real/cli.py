"""Command line of the gap tool: ``crisp gap diagnose`` and ``crisp gap bench``.

``diagnose`` reads logs in the real-log npz format, servo JSON logs (``*.json``) or Go2
``traj_*.npz`` files (recognised by their keys); ``--model`` is the MJCF the npz logs
were recorded on (servo logs carry their own model, Go2 logs default to the
``go2.xml`` beside them).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import mujoco
import tyro

from crisp_gym.file_errors import reading
from crisp_gym.npz import read_npz
from crisp_gym.sim2real import bench
from crisp_gym.sim2real.adapters import load_go2_npz, load_servo_json
from crisp_gym.sim2real.diagnose import DiagnoseConfig, diagnose
from crisp_gym.sim2real.log import RealLog, load_log
from crisp_gym.sim2real.models import add_support_slot
from crisp_gym.sim2real.report import write_report


@dataclass(frozen=True)
class Diagnose:
    """Diagnose the sim-to-real gap of real logs against a MuJoCo model."""

    real: tuple[Path, ...]
    """Real logs to fit on (npz, servo JSON, or Go2 traj npz)."""
    out: Annotated[Path, tyro.conf.arg(aliases=["-o"])] = Path("gap_report")
    """Report folder (report.json, report.md, plots)."""
    model: Path | None = None
    """MJCF the npz logs were recorded on."""
    holdout: tuple[Path, ...] = ()
    """Logs to rank effects on; without them the last part of every log is held out."""
    config: DiagnoseConfig = field(default_factory=DiagnoseConfig)


@dataclass(frozen=True)
class Bench:
    """Blind benchmark: synthetic logs with a hidden effect, diagnosed without the truth."""

    out: Annotated[Path, tyro.conf.arg(aliases=["-o"])] = Path("gap_bench")
    """Folder for the cases' truth, the results table and the summary."""
    cases: int = 42
    """Number of cases, spread round-robin over the models."""
    seed: int = 0
    noise_scale: tuple[float, ...] = (1.0,)
    """Multiples of the encoder noise to sweep (signal-to-noise)."""
    models: tuple[str, ...] = bench.BenchConfig.models
    """Bench models: servo, go2, humanoid, arm, rail_leg."""
    families: tuple[str, ...] = ()
    """Draw in-library effects of these families only (default: all)."""
    config: DiagnoseConfig = field(default_factory=lambda: DiagnoseConfig(show_progress=False))
    """The diagnosis's settings for every case."""


def load_any(path: Path, model_path: Path | None) -> tuple[RealLog, mujoco.MjSpec]:
    """A log and its model, whatever its format."""
    if not path.is_file():
        raise FileNotFoundError(f"log not found: {path}")
    with reading(path, "real log"):
        return _load_log(path, model_path)


def _load_log(path: Path, model_path: Path | None) -> tuple[RealLog, mujoco.MjSpec]:
    if path.suffix == ".json":
        return load_servo_json(path)
    keys = set(read_npz(path, "real log (npz or servo JSON)"))
    if {"dof_pos", "des_dof_pos"} <= keys:
        return load_go2_npz(path, model_path if model_path and model_path.suffix == ".xml" else None)
    if model_path is None:
        raise ValueError(f"{path} is a real-log npz: pass the MJCF it was recorded on with --model")
    if not model_path.is_file():
        raise FileNotFoundError(f"model not found: {model_path}")
    # The parked placeholder lets the library try a support the scene lacks (inert otherwise).
    return load_log(path), add_support_slot(mujoco.MjSpec.from_file(str(model_path)))


def run_diagnose(args: Diagnose) -> int:
    train = [load_any(p, args.model) for p in args.real]
    holdout = [load_any(p, args.model) for p in args.holdout] or None
    result = diagnose(train, holdout, args.config)
    write_report(result, args.out)
    sel = result.selected or result.closest
    print(f"verdict: {result.verdict}; effect: {sel['effect'] if sel else '-'}; held-out gap "
          f"{result.gap_before:.4g} -> {result.gap_after_heldout:.4g} rad (floor {result.noise_floor:.3g}); "
          f"report in {args.out}")
    return 0


def run_bench(args: Bench) -> int:
    summary = bench.run_bench(bench.BenchConfig(cases=args.cases, seed=args.seed, noise_scales=args.noise_scale,
                                                models=args.models, families=args.families), args.out, args.config)
    print(json.dumps(summary, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point: ``diagnose ...`` or ``bench ...``; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    cmd = tyro.extras.subcommand_cli_from_dict({"diagnose": Diagnose, "bench": Bench}, args=argv,
                                                prog="crisp gap")
    try:
        return run_diagnose(cmd) if isinstance(cmd, Diagnose) else run_bench(cmd)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
