"""Atomic writes survive kills: stale temporaries are cleaned, an interrupted replacement is undone,
concurrent writers never share a temporary, and results get a mkdir's / open()'s permissions."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from crisp_gym import atomic
from crisp_gym.atomic import atomic_directory, atomic_path, remove_stale_temporaries, write_text


def _dead_pid() -> int:
    """The pid of a process that has exited (and been reaped)."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def _hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_temporaries_of_dead_writers_are_removed_and_others_kept(tmp_path):
    host = socket.gethostname()
    dead = tmp_path / f".clip.tmp-{host}-{_dead_pid()}-abc123"
    dead.mkdir()
    (dead / "motion.npz").write_bytes(b"half")
    dead_file = tmp_path / f".clip.tmp-{host}-{_dead_pid()}-x_9.npz"
    dead_file.write_bytes(b"half")
    alive = tmp_path / f".clip.tmp-{host}-{os.getpid()}-def456"
    alive.mkdir()
    other_host = tmp_path / f".clip.tmp-elsewhere-{_dead_pid()}-ghi789"
    other_host.mkdir()
    other_clip = tmp_path / f".clip2.tmp-{host}-{_dead_pid()}-jkl012"
    other_clip.mkdir()

    removed = remove_stale_temporaries(tmp_path / "clip")
    assert sorted(removed) == sorted([dead, dead_file])
    assert not dead.exists() and not dead_file.exists()
    assert alive.exists() and other_host.exists() and other_clip.exists()


def test_the_next_write_cleans_what_a_killed_one_left(tmp_path):
    stale = tmp_path / f".out.tmp-{socket.gethostname()}-{_dead_pid()}-abc"
    stale.mkdir()
    with atomic_directory(tmp_path / "out") as tmp:
        (tmp / "a.txt").write_text("a")
    assert _hidden(tmp_path) == [] and (tmp_path / "out" / "a.txt").read_text() == "a"
    stale_file = tmp_path / f".x.json.tmp-{socket.gethostname()}-{_dead_pid()}-abc.json"
    stale_file.write_text("{")
    write_text(tmp_path / "x.json", "{}")
    assert _hidden(tmp_path) == [] and (tmp_path / "x.json").read_text() == "{}"


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "two-renames"])
def test_overwrite_replaces_the_whole_folder(tmp_path, monkeypatch, exchange):
    if not exchange:
        monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    out = tmp_path / "out"
    with atomic_directory(out) as tmp:
        (tmp / "old_only.txt").write_text("old")
        (tmp / "both.txt").write_text("old")
    with pytest.raises(FileExistsError, match="pass overwrite=True"):
        with atomic_directory(out):
            pass
    with atomic_directory(out, overwrite=True) as tmp:
        (tmp / "both.txt").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["both.txt"]  # nothing of the old folder mixed in
    assert (out / "both.txt").read_text() == "new" and _hidden(tmp_path) == []


def test_a_replacement_killed_between_its_renames_is_undone(tmp_path):
    """Without an atomic exchange the old folder is first renamed to a backup: a kill there used to
    leave only the backup, which the next run deleted. The next write now puts it back first."""
    out, backup = tmp_path / "out", tmp_path / ".out.old"
    backup.mkdir()
    (backup / "good.txt").write_text("previous result")
    with pytest.raises(FileExistsError):
        with atomic_directory(out):
            pass
    assert (out / "good.txt").read_text() == "previous result" and not backup.exists()
    backup.mkdir()  # killed after the second rename: the new folder is in place, the backup is stale
    (backup / "good.txt").write_text("older")
    with atomic_directory(out, overwrite=True) as tmp:
        (tmp / "new.txt").write_text("new")
    assert [p.name for p in out.iterdir()] == ["new.txt"] and _hidden(tmp_path) == []


def test_a_failed_block_leaves_the_previous_result_and_no_temporary(tmp_path):
    out = tmp_path / "out"
    with atomic_directory(out) as tmp:
        (tmp / "a.txt").write_text("a")
    with pytest.raises(RuntimeError):
        with atomic_directory(out, overwrite=True) as tmp:
            (tmp / "a.txt").write_text("half")
            raise RuntimeError("interrupted")
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "f.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert (out / "a.txt").read_text() == "a" and not (tmp_path / "f.txt").exists() and _hidden(tmp_path) == []


def test_concurrent_writers_get_their_own_temporaries(tmp_path):
    target = tmp_path / "policy.pt"
    with atomic_path(target) as first, atomic_path(target) as second:
        assert first != second and first.suffix == second.suffix == ".pt"
        first.write_text("first")
        second.write_text("second")
    assert target.read_text() == "first"  # the block that finishes last wins
    assert _hidden(tmp_path) == []


def test_results_get_the_permissions_of_a_plain_write(tmp_path):
    old = os.umask(0o022)
    try:
        path = write_text(tmp_path / "a.txt", "a")
        with atomic_directory(tmp_path / "d"):
            pass
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "d").stat().st_mode & 0o777 == 0o755


_SLOW_WRITER = """
import sys, time
from pathlib import Path
from crisp_gym.atomic import atomic_directory
with atomic_directory(Path(sys.argv[1]), overwrite=True) as tmp:
    for k in range(200):
        (tmp / f"part{k:03d}.txt").write_text("new")
        time.sleep(0.005)
"""


def test_sigkill_at_any_moment_keeps_the_old_folder_or_the_whole_new_one(tmp_path):
    out = tmp_path / "out"
    with atomic_directory(out) as tmp:
        (tmp / "old.txt").write_text("old")
    env = os.environ | {"PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    for delay in (0.0, 0.25, 0.5, 0.75, 1.0):  # after the writer has started writing; it needs ~1 s
        writer = subprocess.Popen([sys.executable, "-c", _SLOW_WRITER, str(out)], env=env)
        deadline = time.monotonic() + 60
        while not any(p.name.startswith(f".out.tmp-{socket.gethostname()}-{writer.pid}-") for p in tmp_path.iterdir()):
            assert writer.poll() is None and time.monotonic() < deadline, "the writer never started writing"
            time.sleep(0.01)
        time.sleep(delay)
        writer.send_signal(signal.SIGKILL)
        writer.wait()
        names = sorted(p.name for p in out.iterdir())
        assert names in (["old.txt"], [f"part{k:03d}.txt" for k in range(200)])
    assert _hidden(tmp_path), "no kill fell inside a write: the delays test nothing"
    with atomic_directory(out, overwrite=True) as tmp:
        (tmp / "old.txt").write_text("old")
    assert _hidden(tmp_path) == []


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_a_folder_that_takes_no_files_is_named_not_the_temporary():
    """``crisp export -o /proc/x`` said "No such file or directory: '/proc/.x.tmp-…'"."""
    with pytest.raises(ValueError, match=r"cannot write /proc/x: /proc does not take new files"):
        with atomic_directory(Path("/proc/x")):
            pass
    with pytest.raises(ValueError, match=r"cannot write /proc/x.json: /proc does not take new files"):
        write_text(Path("/proc/x.json"), "{}")
