"""Writing files so that nothing already written is lost: a result replaces its old version only
once it is whole, a failure (a full disk, a read-only folder, Ctrl-C) leaves the old one and no
half-written file, and the error names the file the user asked for, not a temporary one.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def check_writable(path: str | os.PathLike, what: str = "output") -> Path:
    """``path`` (a file or directory to create or replace) if its folder, or the nearest one
    that exists, can be written; ValueError naming it otherwise. For the door of a long run
    (calibrate, export, training), so that it does not fail at the end."""
    path = Path(path)
    existing = next(p for p in (path.parent, *path.parent.parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"{path}: cannot write the {what} there ({existing} is not a writable directory)")
    return path


@contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary file beside ``path`` for the block to write; synced and moved onto ``path`` (an
    atomic rename, keeping an existing file's permissions) when the block ends, removed when it
    raises. An OSError on the way (no space left, no permission) names ``path``."""
    path = Path(path)
    try:
        mode = path.stat().st_mode & 0o777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    temporary: Path | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
        os.close(handle)
        temporary = Path(name)
        yield temporary
        with temporary.open("rb+") as written:
            os.fsync(written.fileno())
        temporary.chmod(mode)
        os.replace(temporary, path)
    except OSError as error:
        if temporary is not None:
            temporary.unlink(missing_ok=True)
        raise OSError(error.errno, error.strerror or str(error), str(path)) from None
    except BaseException:
        if temporary is not None:
            temporary.unlink(missing_ok=True)
        raise


def write_text(path: str | os.PathLike, text: str) -> None:
    """``text`` into ``path``, replacing it whole or not at all (:func:`replacing`)."""
    with replacing(path) as temporary:
        temporary.write_text(text)
