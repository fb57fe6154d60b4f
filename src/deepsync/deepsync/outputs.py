"""Writing files so that nothing already written is lost: a result replaces its old version only
once it is whole, a failure (a full disk, a read-only folder, Ctrl-C) leaves the old one and no
half-written file, and the error names the file the user asked for, not a temporary one.
"""

from __future__ import annotations

import glob
import os
import shutil
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
    try:  # a file made and removed: the one test that holds for root, read-only mounts and /proc alike
        if not existing.is_dir():
            raise NotADirectoryError(f"{existing} is not a directory")
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as error:
        raise ValueError(f"{path}: cannot write the {what} there ({existing}: "
                         f"{error.strerror or error})") from None
    return path


def partial_prefix(path: Path) -> str:
    """How the partial files and directories being written for ``path`` are named (hidden,
    beside it, with the writing process's id): ``.NAME.PID.`` ... ``.partial``."""
    return f".{path.name}.{os.getpid()}."


def remove_abandoned(path: str | os.PathLike) -> list[Path]:
    """Remove what writers of ``path`` that are gone (killed: SIGKILL, a power cut) left beside it,
    the ``.NAME.PID.*.partial`` of a process that no longer runs; what live writers are writing
    stays. Returns what was removed."""
    path = Path(path)
    removed = []
    for partial in path.parent.glob(f".{glob.escape(path.name)}.*.partial"):
        pid = partial.name[len(path.name) + 2 :].split(".", 1)[0]
        if not pid.isdigit() or _alive(int(pid)):
            continue
        if partial.is_dir() and not partial.is_symlink():
            shutil.rmtree(partial, ignore_errors=True)
        else:
            partial.unlink(missing_ok=True)
        removed.append(partial)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):
        return False
    except PermissionError:  # another user's process
        return True
    return True


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
        remove_abandoned(path)
        handle, name = tempfile.mkstemp(prefix=partial_prefix(path), suffix=".partial", dir=path.parent)
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
