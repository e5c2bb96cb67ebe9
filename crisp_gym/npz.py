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
from pathlib import Path

import numpy as np

_NPY = ".npy"


def _declared_bytes(member, path: Path, name: str) -> tuple[int, np.dtype]:
    """(bytes the array header of an open ``.npy`` member declares, its dtype)."""
    version = np.lib.format.read_magic(member)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(member)
    elif version in ((2, 0), (3, 0)):
        shape, _, dtype = np.lib.format.read_array_header_2_0(member)
    else:
        raise ValueError(f"{path}: member {name} has an unknown .npy format version {version}")
    count = 1
    for n in shape:
        count *= int(n)
    return count * dtype.itemsize, dtype


def read_npz(path: str | Path, what: str, skip_objects: bool = False) -> dict[str, np.ndarray]:
    """The arrays of the ``.npz`` at ``path`` (a ``what``: named in errors) by member name.

    Object arrays need pickles to load: they are an error, or left out with ``skip_objects``
    (some upstream tools store strings as objects beside the numeric arrays that matter).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no {what} at {path}")
    try:
        with zipfile.ZipFile(path) as archive:
            arrays = {}
            for info in archive.infolist():
                if not info.filename.endswith(_NPY):
                    continue
                name = info.filename[: -len(_NPY)]
                with archive.open(info) as member:
                    declared, dtype = _declared_bytes(member, path, name)
                    data_size = info.file_size - member.tell()
                if dtype.hasobject:
                    if skip_objects:
                        continue
                    raise ValueError(f"{path}: array {name!r} holds Python objects, which only a pickle can load")
                if declared > data_size:
                    raise ValueError(f"{path}: array {name!r} declares {declared:,} bytes but the file holds "
                                     f"{max(data_size, 0):,} (a damaged header)")
                with archive.open(info) as member:
                    arrays[name] = np.lib.format.read_array(member, allow_pickle=False)
    except zipfile.BadZipFile as err:
        with open(path, "rb") as f:
            if f.read(len(np.lib.format.MAGIC_PREFIX)) == np.lib.format.MAGIC_PREFIX:
                raise ValueError(f"{path} holds a single array (.npy); expected a {what}") from None
        raise ValueError(f"{path} is not a readable npz archive ({err}); expected a {what}") from None
    # truncated or bit-flipped data; a damaged .npy header fails in numpy's Python-literal parser
    except (zlib.error, EOFError, OSError, SyntaxError, tokenize.TokenError) as err:
        raise ValueError(f"{path} is a damaged npz archive ({type(err).__name__}: {err}); expected a {what}") from None
    except ValueError as err:
        message = str(err)
        raise ValueError(message if message.startswith(str(path)) else f"{path}: {message}") from None
    return arrays


def read_npy(path: str | Path, what: str) -> np.ndarray:
    """The array of the ``.npy`` at ``path``, checked as :func:`read_npz` checks each member."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no {what} at {path}")
    try:
        with open(path, "rb") as f:
            declared, dtype = _declared_bytes(f, path, path.name)
            data_size = path.stat().st_size - f.tell()
            if dtype.hasobject:
                raise ValueError(f"{path} holds Python objects, which only a pickle can load")
            if declared > data_size:
                raise ValueError(f"{path} declares {declared:,} bytes but holds {max(data_size, 0):,} "
                                 "(a damaged header)")
            f.seek(0)
            return np.lib.format.read_array(f, allow_pickle=False)
    except (EOFError, OSError, SyntaxError, tokenize.TokenError) as err:
        raise ValueError(f"{path} is a damaged .npy file ({type(err).__name__}: {err}); expected a {what}") from None
    except ValueError as err:
        message = str(err)
        raise ValueError(message if message.startswith(str(path)) else f"{path}: {message}") from None
