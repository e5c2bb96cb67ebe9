"""Atomic writes: build a file or a directory under a temporary sibling name, rename it into place.

An interrupted run (Ctrl-C, a crash, a full disk, even SIGKILL) never leaves a half-written clip,
input or export where the result belongs, and never loses the previous one:

- temporaries are hidden siblings named ``.NAME.tmp-HOST-PID-RANDOM[SUFFIX]``: concurrent writers
  never share one, and the next write to ``NAME`` removes those whose process is gone (a SIGKILL
  leaves them behind; nothing else can);
- a directory replaces an existing one with one atomic exchange of the two names where the
  filesystem supports it (Linux ``renameat2``); elsewhere through a backup ``.NAME.old``, which the
  next write puts back if a kill fell between the two renames.
"""

from __future__ import annotations

import ctypes
import errno
import logging
import os
import re
import shutil
import socket
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger(__name__)

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _umask() -> int:
    """The process's umask (reading it means setting it; set it straight back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _temp_prefix(target: Path) -> str:
    return f".{target.name}.tmp-{socket.gethostname()}-{os.getpid()}-"


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_temporaries(target: str | Path) -> list[Path]:
    """Remove the temporaries of ``target`` whose writer process no longer runs on this host
    (left by a SIGKILL or a power loss); returns what was removed. Another host's are kept:
    only that host can tell whether their writer still runs."""
    target = Path(target)
    if not target.parent.is_dir():
        return []
    pattern = re.compile(rf"\.{re.escape(target.name)}\.tmp-(?P<host>.+)-(?P<pid>\d+)-[A-Za-z0-9_]+")
    here = socket.gethostname()
    removed = []
    for sibling in target.parent.iterdir():
        match = pattern.match(sibling.name)
        if not match or match["host"] != here or _process_alive(int(match["pid"])):
            continue
        if sibling.is_dir() and not sibling.is_symlink():
            shutil.rmtree(sibling, ignore_errors=True)
        else:
            sibling.unlink(missing_ok=True)
        removed.append(sibling)
    return removed


@contextmanager
def _writable(target: Path) -> Iterator[None]:
    """A ValueError naming ``target`` when its folder cannot take the temporary (a read-only or
    virtual filesystem such as /proc), instead of an OSError naming the temporary."""
    try:
        yield
    except OSError as err:
        raise ValueError(f"cannot write {target}: {target.parent} does not take new files "
                         f"({err.strerror or err})") from None


def _exchange(a: Path, b: Path) -> bool:
    """Swap the names ``a`` and ``b`` in one atomic step; False where the OS or filesystem cannot."""
    renameat2 = getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)
    if renameat2 is None:
        return False
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):
        return False
    raise OSError(code, f"cannot swap {a} and {b}: {os.strerror(code)}")


def _restore_backup(directory: Path, backup: Path) -> None:
    """Undo a replacement a kill interrupted between its two renames; drop a finished one's backup."""
    if not backup.exists():
        return
    if directory.exists():
        shutil.rmtree(backup, ignore_errors=True)
    else:
        backup.rename(directory)
        log.warning("restored %s from the backup an interrupted replacement left", directory)


def _replace_directory(tmp: Path, directory: Path, backup: Path) -> None:
    if _exchange(tmp, directory):
        shutil.rmtree(tmp)  # now the previous contents
        return
    shutil.rmtree(backup, ignore_errors=True)
    directory.rename(backup)
    tmp.rename(directory)
    shutil.rmtree(backup)


@contextmanager
def atomic_directory(directory: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield an empty temporary directory beside ``directory``; it becomes ``directory`` only if
    the block succeeds (replacing an existing one when ``overwrite``), else it is removed."""
    directory = Path(directory)
    backup = directory.with_name(f".{directory.name}.old")
    remove_stale_temporaries(directory)
    _restore_backup(directory, backup)
    if directory.exists() and not overwrite:
        raise FileExistsError(f"{directory} exists; pass overwrite=True (--overwrite) to replace it")
    with _writable(directory):
        directory.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(directory), dir=directory.parent))
    tmp.chmod(0o777 & ~_umask())  # mkdtemp's 0700 would make the result private, unlike a mkdir
    try:
        yield tmp
        if directory.exists():
            _replace_directory(tmp, directory, backup)
        else:
            tmp.rename(directory)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; it replaces ``path`` only if the block succeeds.

    The temporary name keeps ``path``'s suffix, so libraries that infer the file type from the
    name (numpy, trimesh, torch) still do. An interrupted write never leaves a half-written file.
    """
    path = Path(path)
    with _writable(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(path)
        handle, name = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=path.suffix, dir=path.parent)
    os.close(handle)
    tmp = Path(name)
    tmp.chmod(0o666 & ~_umask())  # mkstemp's 0600 would make the result private, unlike an open()
    try:
        yield tmp
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically; returns ``path``."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def save_figure(fig, path: str | Path) -> None:
    """Lay out, write atomically (100 dpi) and close a matplotlib figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
