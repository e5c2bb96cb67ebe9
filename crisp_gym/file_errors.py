"""One error for a file whose content a loader cannot interpret, and it names the file.

Loaders check what they can name (missing keys, shapes, ranges) with messages that say what is
expected, but checks deep in shared code (a motion's shapes, a log's lengths) do not know which
file the values came from, and a damaged file can fail in indexing or arithmetic no check
foresaw. :func:`reading` turns both into a ValueError that starts with the file, which the CLI
reports in one line (``--debug`` shows the chained traceback).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

CONTENT_ERRORS = (IndexError, KeyError, TypeError, AttributeError, ZeroDivisionError, OverflowError)
"""What interpreting a damaged file's values raises besides ValueError."""


@contextmanager
def reading(path: str | Path, what: str) -> Iterator[None]:
    """Re-raise :data:`CONTENT_ERRORS` from the block as a ValueError naming ``path`` (a ``what``),
    and prefix ``path`` to ValueErrors that do not name it."""
    try:
        yield
    except CONTENT_ERRORS as err:
        raise ValueError(f"{path}: a damaged or inconsistent {what} ({type(err).__name__}: {err})") from err
    except ValueError as err:
        if str(path) in str(err):
            raise
        raise ValueError(f"{path}: {err}") from err
