"""Reading users' ``.npz`` archives: no pickles, no allocation the file does not back, and every
kind of damage a one-line ValueError naming the file.

``numpy.load`` allocates whatever an array header declares before reading a byte of data: a
flipped bit in a shape turns a 1 kB file into a request for terabytes (a MemoryError) or a few
gigabytes that are allocated and then found missing. Here each member's header is read first and
its array must fit in the member's own uncompressed size, as recorded in the archive.
"""

from __future__ import annotations

import tokenize
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from crisp_gym.file_errors import reading

_NPY = ".npy"


def _check_header(stream, size: int, path: Path, name: str, skip_objects: bool) -> bool:
    """Read the header of the ``.npy`` data in ``stream`` (``size`` bytes in all): False for an
    object array that ``skip_objects`` leaves out, a ValueError when the array needs a pickle or
    declares more bytes than the data holds, else True."""
    version = np.lib.format.read_magic(stream)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(stream)
    elif version in ((2, 0), (3, 0)):
        shape, _, dtype = np.lib.format.read_array_header_2_0(stream)
    else:
        raise ValueError(f"{path}: array {name!r} has an unknown .npy format version {version}")
    if dtype.hasobject:
        if skip_objects:
            return False
        raise ValueError(f"{path}: array {name!r} holds Python objects, which only a pickle can load")
    declared, held = int(np.prod(shape, dtype=object)) * dtype.itemsize, size - stream.tell()
    if declared > held:
        raise ValueError(f"{path}: array {name!r} declares {declared:,} bytes but the file holds {max(held, 0):,} "
                         "(a damaged header)")
    return True


@contextmanager
def _damage_named(path: Path, what: str, kind: str) -> Iterator[None]:
    """Truncated or bit-flipped data (numpy's Python-literal header parser included) as a ValueError
    naming the file; other ValueErrors get the file's name in front (:func:`reading`)."""
    with reading(path, what):
        try:
            yield
        except (zlib.error, EOFError, OSError, SyntaxError, tokenize.TokenError) as err:
            raise ValueError(f"{path} is a damaged {kind} ({type(err).__name__}: {err}); expected a {what}") from None


def read_npz(path: str | Path, what: str, skip_objects: bool = False) -> dict[str, np.ndarray]:
    """The arrays of the ``.npz`` at ``path`` (a ``what``: named in errors) by member name.

    Object arrays need pickles to load: they are an error, or left out with ``skip_objects``
    (some upstream tools store strings as objects beside the numeric arrays that matter).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no {what} at {path}")
    arrays = {}
    with _damage_named(path, what, "npz archive"):
        try:
            with zipfile.ZipFile(path) as archive:
                for info in archive.infolist():
                    if not info.filename.endswith(_NPY):
                        continue
                    name = info.filename[: -len(_NPY)]
                    with archive.open(info) as member:
                        if not _check_header(member, info.file_size, path, name, skip_objects):
                            continue
                    with archive.open(info) as member:
                        arrays[name] = np.lib.format.read_array(member, allow_pickle=False)
        except zipfile.BadZipFile as err:
            with open(path, "rb") as f:
                if f.read(len(np.lib.format.MAGIC_PREFIX)) == np.lib.format.MAGIC_PREFIX:
                    raise ValueError(f"{path} holds a single array (.npy); expected a {what}") from None
            raise ValueError(f"{path} is not a readable npz archive ({err}); expected a {what}") from None
    return arrays


def read_npy(path: str | Path, what: str) -> np.ndarray:
    """The array of the ``.npy`` at ``path``, checked as :func:`read_npz` checks each member."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no {what} at {path}")
    with _damage_named(path, what, ".npy file"), open(path, "rb") as f:
        _check_header(f, path.stat().st_size, path, path.name, skip_objects=False)
        f.seek(0)
        return np.lib.format.read_array(f, allow_pickle=False)
