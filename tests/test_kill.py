"""SIGKILL at random moments of ``crisp reconstruct``, ``import-motion``, ``export`` and ``train``:
the output is always either the previous good one or the whole new one (never a folder that looks
valid but is not, never nothing where there was something), and the next run leaves no temporaries.

Each command first runs to the end twice, writing the new and then the old output (the second's
duration sets the kill window); then the new one runs again over the old with ``--overwrite`` (or
``--resume``) and is killed at seeded random times. The default suite kills each command a few
times; ``-m slow`` many times.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from crisp_gym.clip import load_clip_dir
from tests.conftest import small_synth_input

REPO = Path(__file__).resolve().parents[1]
CRISP = [sys.executable, "-m", "crisp_gym.cli"]
KILLS = pytest.mark.parametrize("kills", [pytest.param(3, id="3-kills"),
                                          pytest.param(25, id="25-kills", marks=pytest.mark.slow)])


def _run(argv: list[str], cwd: Path) -> float:
    """Run a command to the end; its wall time."""
    start = time.perf_counter()
    subprocess.run(argv, cwd=cwd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def _kill_repeatedly(argv: list[str], cwd: Path, window: float, kills: int, seed: int,
                     check: Callable[[], None]) -> None:
    """Start ``argv`` ``kills`` times, SIGKILL it after a uniform random time in ``window`` and
    ``check`` what it left."""
    rng = np.random.default_rng(seed)
    for _ in range(kills):
        proc = subprocess.Popen(argv, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            proc.wait(timeout=rng.uniform(0.0, window))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        check()


def _content(path: Path) -> bytes:
    """A file's bytes; for JSON, without the wall-clock ``*timings`` that differ from run to run."""
    if path.suffix != ".json":
        return path.read_bytes()
    content = json.loads(path.read_text())
    if isinstance(content, dict):
        content = {k: v for k, v in content.items() if not k.endswith("timings")}
    return json.dumps(content, sort_keys=True).encode()


def _fingerprint(folder: Path) -> dict[str, str]:
    """Relative path -> SHA-1 of every file under ``folder`` (hidden temporaries included)."""
    return {str(p.relative_to(folder)): hashlib.sha1(_content(p)).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _no_temporaries(folder: Path) -> None:
    leftovers = [p.name for p in folder.iterdir() if p.name.startswith(".")]
    assert leftovers == [], f"temporaries left after a complete run: {leftovers}"


def _kill_test_over_previous_output(argv_old: list[str], argv_new: list[str], out: Path, cwd: Path, kills: int,
                                    seed: int, loads: Callable[[Path], object]) -> None:
    """Write ``out`` with ``argv_old``, then kill ``argv_new`` (which overwrites it) repeatedly: ``out``
    must always be exactly the old output or exactly the new one, and load."""
    _run(argv_new, cwd)
    new = _fingerprint(out)
    window = _run(argv_old, cwd)
    old = _fingerprint(out)
    assert new != old

    def check() -> None:
        assert out.is_dir(), "the previous good output is gone"
        assert _fingerprint(out) in (old, new), "a mix of two outputs, or a partial one"
        loads(out)

    _kill_repeatedly(argv_new, cwd, window, kills, seed, check)
    _run(argv_new, cwd)
    assert _fingerprint(out) == new
    _no_temporaries(out.parent)


@KILLS
def test_import_motion_killed_keeps_a_whole_clip(tmp_path, kills):
    clips = REPO / "assets" / "clips"
    out = tmp_path / "clips" / "imported"
    common = ["--name", "imported", "-o", str(out), "--overwrite"]
    _kill_test_over_previous_output(
        [*CRISP, "import-motion", str(clips / "flat_walk" / "motion.npz"), *common],
        [*CRISP, "import-motion", str(clips / "stairs_up" / "motion.npz"), *common],
        out, tmp_path, kills, seed=1, loads=load_clip_dir)


@KILLS
def test_export_killed_keeps_a_whole_export(tmp_path, kills):
    out = tmp_path / "export"
    common = ["--format", "all", "-o", str(out), "--overwrite"]

    def loads(folder: Path) -> None:
        import mujoco

        mujoco.MjModel.from_xml_path(str(folder / "mjcf" / "track.xml"))

    _kill_test_over_previous_output([*CRISP, "export", "flat_walk", *common], [*CRISP, "export", "stairs_up", *common],
                                    out, tmp_path, kills, seed=2, loads=loads)


@pytest.fixture(scope="module")
def small_video_input(tmp_path_factory) -> Path:
    return small_synth_input(tmp_path_factory.mktemp("synth") / "platform", "platform_step", 5)


@KILLS
def test_reconstruct_killed_keeps_a_whole_clip(tmp_path, kills, small_video_input):
    out = tmp_path / "clips" / "recon"
    source = ["--motion", str(small_video_input / "motion_camera.npz"), "-o", str(out), "--overwrite"]
    _kill_test_over_previous_output(
        [*CRISP, "reconstruct", str(small_video_input / "input.npz"), *source, "--contacts", "none"],
        [*CRISP, "reconstruct", str(small_video_input / "input.npz"), *source],
        out, tmp_path, kills, seed=3, loads=load_clip_dir)


@KILLS
def test_train_killed_keeps_a_checkpoint_that_resumes(tmp_path, kills):
    """A killed run keeps its last checkpoint whole (it loads, and never goes back in time), and
    ``--resume`` finishes the run."""
    from crisp_gym.policy.files import load_checkpoint

    run = tmp_path / "run"

    def argv(frames: int) -> list[str]:
        return [*CRISP, "train", "--clip", "flat_walk", "-o", str(run), "--frames", str(frames), "--num-envs", "8",
                "--steps-per-env", "8", "--minibatch-size", "32", "--epochs", "1", "--checkpoint-every", "1",
                "--eval-every", "0", "--no-progress", "--seed", "4"]

    window = 2 * _run(argv(1024), tmp_path)  # start-up and a few checkpoints
    reached = [load_checkpoint(run)["frames"]]

    def check() -> None:
        state = load_checkpoint(run)  # loads: never missing once written, never half-written
        assert state["frames"] >= reached[-1], "a kill lost a checkpoint that had been written"
        reached.append(state["frames"])

    final = 4096
    _kill_repeatedly([*argv(final), "--resume"], tmp_path, window, kills, seed=4, check=check)
    _run([*argv(final), "--resume"], tmp_path)
    assert load_checkpoint(run)["frames"] == final
    _no_temporaries(run)
