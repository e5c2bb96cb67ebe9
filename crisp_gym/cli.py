"""The ``crisp`` command: one subcommand per job, each a module with ``main(argv) -> int``.

Subcommand modules are imported only when run, so ``crisp --help`` and light commands do
not pay for torch or open3d. A user error (a bad value, a missing or unreadable file, an output
that exists) ends any subcommand with one line naming it and exit status 2; ``crisp --debug
COMMAND ...`` shows the traceback instead. Output piped into a reader that leaves early
(``crisp train --help | head``) ends quietly, with exit status 1.
"""

from __future__ import annotations

import importlib
import os
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("crisp_gym.train.demo", "run the demo on a bundled clip: rollout, report and video"),
    "clips": ("crisp_gym.clips_cli", "list the registered clips"),
    "import-motion": ("crisp_gym.import_motion", "make a flat-ground clip from a BVH/SMPL/motion.npz file"),
    "synth-clips": ("crisp_gym.synth.clips", "regenerate the bundled synthetic clips, or make one more (--kind, --seed)"),
    "synth": ("crisp_gym.synth.video_cli", "render a synthetic depth video with ground truth"),
    "reconstruct": ("crisp_gym.reconstruct.pipeline", "reconstruct a clip from a depth video and a human motion"),
    "reconstruct-all": ("crisp_gym.reconstruct.batch", "reconstruct every input of a folder as its own clip, in parallel on Ray"),
    "feasibility": ("crisp_gym.feasibility", "search for actions that track a clip: is its reference feasible?"),
    "export": ("crisp_gym.export", "export a clip or a policy for other stacks (MJCF, URDF, GLB, CSV, ONNX)"),
    "train": ("crisp_gym.train.cli", "train a tracking policy with PPO"),
    "eval": ("crisp_gym.train.evaluate", "evaluate a trained policy on a clip: metrics, plots, video"),
    "ship": ("crisp_gym.train.ship", "package a run for shipping: policy file, evaluation, learning curves"),
    "view": ("crisp_gym.train.view", "an interactive 3D viewer in the browser: a clip, its reference and a policy's rollout"),
    "gap": ("crisp_gym.sim2real.cli", "sim-to-real gap: `crisp gap diagnose` / `crisp gap bench`"),
}


USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError,
               PermissionError, ModuleNotFoundError)
"""Exceptions that report what the user asked for wrongly (or an optional extra not installed),
not a fault of the program."""


def _usage() -> str:
    lines = ["usage: crisp [--debug] COMMAND [ARGS...]", "", "commands:"]
    width = max(map(len, COMMANDS)) + 1
    lines += [f"  {name:<{width}} {help_}" for name, (_, help_) in COMMANDS.items()]
    lines += ["", "`crisp COMMAND --help` describes a command's options; `--debug` shows tracebacks of errors."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = bool(argv) and argv[0] == "--debug"
    argv = argv[1:] if debug else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"crisp: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[name][0])
    try:
        result = module.main(rest)
        sys.stdout.flush()
    except USER_ERRORS as err:
        if debug:
            raise
        print(f"crisp {name}: {err}\n(crisp --debug {name} ... shows the traceback)", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader of the output left (`crisp train --help | head`): stop quietly, as Unix tools
        # do, and point stdout at /dev/null so that the interpreter's last flush does not fail too.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
