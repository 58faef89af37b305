"""Atomic writes: a temp file (or folder) beside the target, then one rename over it.

A reader sees the old file or the new one, never half of one. One behaviour everywhere: the
temp file is created with mode 0o666 and the folder with 0o777, both filtered by the user's
umask (so results get the same mode as any file the user writes, not mkstemp's private 0600),
the data are fsynced before the rename, and the temp file is removed when writing fails.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path
from typing import BinaryIO, Callable

_ATTEMPTS = 100


def _unique_sibling(parent: Path, prefix: str, suffix: str, create: Callable[[Path], None]
                    ) -> Path:
    for _ in range(_ATTEMPTS):
        candidate = parent / f'{prefix}{secrets.token_hex(4)}{suffix}'
        try:
            create(candidate)
        except FileExistsError:
            continue
        return candidate
    raise FileExistsError(f'no free temporary name {prefix}XXXXXXXX{suffix} in {parent}')


def make_temp_dir(parent: str | Path, prefix: str) -> Path:
    """A new empty folder `<parent>/<prefix>XXXXXXXX`, mode 0o777 filtered by the umask."""
    return _unique_sibling(Path(parent), prefix, '', lambda p: os.mkdir(p, 0o777))


def replace(src: str | Path, dst: str | Path) -> None:
    """Rename `src` over `dst` in one step (a file over a file, or a folder to a new name)."""
    os.replace(src, dst)


def write_atomic(path: str | Path, write: Callable[[BinaryIO], object]) -> Path:
    """Call `write(f)` on a binary temp file beside `path`, fsync it, rename it over `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fds: list[int] = []

    def create(candidate: Path) -> None:
        fds.append(os.open(candidate, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))

    tmp = _unique_sibling(path.parent, f'.{path.name}.', '.tmp', create)
    try:
        with os.fdopen(fds[0], 'wb') as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write `text` (UTF-8) to `path` atomically."""
    return write_atomic(path, lambda f: f.write(text.encode('utf-8')))
