"""The ``crisp`` dispatcher: user errors end any subcommand with one line and exit status 2."""

from __future__ import annotations

import pytest

from crisp_gym import cli
from crisp_gym.registry import user_registry_path


def _corrupt_registry() -> None:
    registry = user_registry_path()
    registry.parent.mkdir(parents=True, exist_ok=True)
    registry.write_text("clips:\n  a: [unclosed\n")


def test_a_corrupt_registry_is_one_line_naming_the_file(tmp_path, capsys):
    _corrupt_registry()
    assert cli.main(["export", "flat_walk", "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert str(user_registry_path()) in err and "Traceback" not in err and "--debug" in err
    assert not (tmp_path / "out").exists()


def test_debug_shows_the_traceback(tmp_path):
    _corrupt_registry()
    with pytest.raises(ValueError, match="not a readable registry"):
        cli.main(["--debug", "export", "flat_walk", "-o", str(tmp_path / "out")])


@pytest.mark.parametrize("argv, message", [
    (["eval", "/nonexistent-run"], "no policy at"),
    (["import-motion", "/nonexistent.npz", "--name", "x"], "no motion file"),
    (["export", "no-such-clip", "--format", "csv"], "no-such-clip"),
])  # fmt: skip
def test_user_errors_exit_2(argv, message, capsys):
    assert cli.main(argv) == 2
    assert message in capsys.readouterr().err


def test_unknown_command_and_help(capsys):
    assert cli.main(["nope"]) == 2
    assert cli.main(["--help"]) == 0 and "--debug" in capsys.readouterr().out


def test_help_into_a_closed_pipe_ends_quietly():
    """`crisp train --help | head -1`: the reader leaves early; no traceback, no "Exception ignored"."""
    import os
    import subprocess
    import sys

    read_end, write_end = os.pipe()
    os.close(read_end)  # every write to the pipe now fails with EPIPE, as after `head` exits
    try:
        done = subprocess.run([sys.executable, "-m", "crisp_gym.cli", "train", "--help"], stdout=write_end,
                              stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write_end)
    assert done.returncode == 1 and done.stderr == ""


def test_unreadable_policy_files_are_named(tmp_path, capsys):
    """A garbage file and a truncated real policy: one line naming the file, no traceback."""
    from pathlib import Path

    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a torch file")
    shipped = Path(__file__).resolve().parents[1] / "assets" / "policies" / "flat_walk" / "policy.pt"
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(shipped.read_bytes()[:1000])
    for path, message in ((garbage, "not a torch file"), (truncated, "not a readable torch file")):
        assert cli.main(["eval", str(path)]) == 2
        err = capsys.readouterr().err
        assert str(path) in err and message in err and "Traceback" not in err


@pytest.mark.parametrize("damage, message", [
    (lambda clip: (clip / "motion.npz").write_bytes((clip / "motion.npz").read_bytes()[:500]),
     "motion.npz is not a readable npz"),
    (lambda clip: (clip / "meta.json").write_text("{bad"), "meta.json is not valid JSON"),
    (lambda clip: (clip / "primitives.json").write_text("[1,"), "primitives.json is not valid JSON"),
])  # fmt: skip
def test_a_damaged_clip_is_named(damage, message, tmp_path, capsys):
    import shutil
    from pathlib import Path

    clip = tmp_path / "clip"
    shutil.copytree(Path(__file__).resolve().parents[1] / "assets" / "clips" / "flat_walk", clip)
    damage(clip)
    assert cli.main(["export", str(clip), "--format", "csv", "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and not (tmp_path / "out").exists()
