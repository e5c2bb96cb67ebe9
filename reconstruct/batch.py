"""``crisp reconstruct-all FOLDER -o OUT``: every input in a folder reconstructed as its own clip, in
parallel on Ray: a local cluster of this machine's cores by default, an existing cluster with
``--address`` (``auto`` on a cluster node, or ``ray://HEAD:10001``). See ``docs/scaling.md``.

An input is an item of ``FOLDER``:

* a folder holding ``input.npz`` (MegaSAM layout) and, optionally, the motion as
  ``motion_camera.npz``, ``motion.npz`` or one ``.bvh``;
* an RGB-D folder (TUM or Redwood layout) or a plain video (a video file or an image folder);
* a MegaSAM ``.npz`` file.

Each becomes ``OUT/<item name>`` exactly as ``crisp reconstruct`` writes it (atomically). An input
that fails does not stop the others: the failures are listed at the end (exit status 2).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated

import tyro
from tqdm.auto import tqdm

from crisp_gym.reconstruct.io import VIDEO_SUFFIXES, is_plain_video
from crisp_gym.reconstruct.pipeline import ReconstructArgs, run
from crisp_gym.registry import register_clip

_MOTION_FILES = ("motion_camera.npz", "motion.npz")


@dataclass(frozen=True)
class BatchArgs:
    """Reconstruct every input of a folder as its own clip, in parallel on Ray."""

    folder: tyro.conf.Positional[Path]
    """The folder of inputs (see the module docstring)."""
    output: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("clips")
    """Where the clips go, one folder per input."""
    address: str | None = None
    """A Ray cluster to join (auto on one of its nodes, or ray://HEAD:10001); default: a local one."""
    num_cpus: int | None = None
    """Cores of the local cluster (default: all); one input per core at a time."""
    metric: bool = False
    """Trust the depth as metres (as crisp reconstruct --metric)."""
    contacts: str = "kinematic"
    """Contact source for every input (kinematic or none)."""
    overwrite: bool = False
    """Replace existing clip folders."""
    register: bool = False
    """Add every clip to the user registry under its folder name."""


def find_inputs(folder: Path) -> list[tuple[str, Path, Path | None]]:
    """(name, input, motion or None) for every input of ``folder``, by name."""
    if not folder.is_dir():
        raise NotADirectoryError(f"no folder of inputs at {folder}")
    found = []
    for item in sorted(folder.iterdir()):
        if item.name.startswith("."):
            continue
        if item.is_dir() and (item / "input.npz").is_file():
            motions = [item / m for m in _MOTION_FILES if (item / m).is_file()] + sorted(item.glob("*.bvh"))
            found.append((item.name, item / "input.npz", motions[0] if motions else None))
        elif item.is_dir() and ((item / "depth").is_dir() or (item / "depth.txt").is_file() or is_plain_video(item)):
            found.append((item.name, item, None))
        elif item.is_file() and (item.suffix.lower() in VIDEO_SUFFIXES or item.suffix.lower() == ".npz"):
            found.append((item.stem, item, None))
    if not found:
        raise ValueError(f"{folder} holds no input (a folder with input.npz, an RGB-D folder, a video or an .npz)")
    return found


def reconstruct_one(args: ReconstructArgs) -> str:
    """One ``crisp reconstruct`` (run in a Ray worker); the clip's folder."""
    return str(run(args))


def main(argv: list[str] | None = None) -> int:
    """``crisp reconstruct-all``: see :class:`BatchArgs`."""
    args = tyro.cli(BatchArgs, args=argv, prog="crisp reconstruct-all")
    inputs = find_inputs(args.folder)
    # registering is the driver's: workers writing the registry at once would lose each other's entries
    base = ReconstructArgs(input=Path(), metric=args.metric, contacts=args.contacts, overwrite=args.overwrite)
    jobs = {name: replace(base, input=source.resolve(), motion=None if motion is None else motion.resolve(),
                          name=name, output=(args.output / name).resolve()) for name, source, motion in inputs}
    try:
        import ray  # noqa: PLC0415 - only this command needs it
    except ModuleNotFoundError:
        raise ModuleNotFoundError("crisp reconstruct-all runs on Ray: pip install 'crisp-gym[scale]'") from None

    ray.init(address=args.address, num_cpus=args.num_cpus if args.address is None else None,
             include_dashboard=False, log_to_driver=False)
    try:
        task = ray.remote(num_cpus=1)(reconstruct_one)
        pending = {task.remote(job): name for name, job in jobs.items()}
        failures: dict[str, str] = {}
        with tqdm(total=len(pending), desc="reconstruct", unit="input") as bar:
            while pending:
                (done,), _ = ray.wait(list(pending), num_returns=1)
                name = pending.pop(done)
                try:
                    clip = ray.get(done)
                except ray.exceptions.RayTaskError as err:
                    cause = err.cause if err.cause is not None else err
                    failures[name] = f"{type(cause).__name__}: {cause}"
                else:
                    if args.register:
                        register_clip(name, clip, tags=["reconstructed"])
                bar.update()
    finally:
        ray.shutdown()
    print(f"wrote {len(jobs) - len(failures)} of {len(jobs)} clips to {args.output}")
    for name, reason in failures.items():
        print(f"  {name}: {reason}")
    return 2 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
