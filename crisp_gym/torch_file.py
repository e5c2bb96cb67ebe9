"""Reading torch files users hand us (policies, checkpoints, ProtoMotions motions): tensors and
plain values only, never code, and a file that cannot be read is one ValueError naming it."""

from __future__ import annotations

import pickle
import struct
from pathlib import Path
from typing import Any

from crisp_gym.file_errors import CONTENT_ERRORS


def load_tensors(path: str | Path) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU, its failures as ValueErrors naming ``path``."""
    import torch  # noqa: PLC0415 - the base library does not need torch at import

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:  # garbage, or objects that only running pickled code would make
        raise ValueError(f"{path} is not a torch file of tensors and plain values (corrupt, or not ours)") from None
    # e.g. a truncated zip archive; a damaged pickle stream fails in the unpickler's own ways, its
    # checks of persistent ids included (assertions) and its unpacking of binary opcodes
    except (RuntimeError, EOFError, OSError, ValueError, struct.error, AssertionError, *CONTENT_ERRORS) as err:
        reason = str(err).strip().split(". ")[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"{path} is not a readable torch file ({reason})") from None
