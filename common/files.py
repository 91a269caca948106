"""Files that appear whole or not at all: written under a temporary name beside the target, then renamed."""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

PARTIAL = ".partial"
"""What a temporary name adds to the target's."""


@contextmanager
def atomic_path(path: str | Path, keep_suffix: bool = False) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to: it replaces ``path`` when the block ends and is
    removed when the block raises, so ``path`` holds a whole file or keeps what it held.

    The temporary name is ``<name>.partial``; with ``keep_suffix`` it is ``<stem>.partial<suffix>``,
    for writers that choose the format by the file's extension.
    """
    path = Path(path)
    tmp = path.with_name(f"{path.stem}{PARTIAL}{path.suffix}" if keep_suffix else f"{path.name}{PARTIAL}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_atomically(path: str | Path, content: str | bytes) -> None:
    """``path`` holds ``content`` whole or keeps what it held."""
    with atomic_path(path) as tmp:
        if isinstance(content, bytes):
            tmp.write_bytes(content)
        else:
            tmp.write_text(content)
