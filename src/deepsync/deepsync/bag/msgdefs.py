"""Where the deepsync_msgs definitions live, and the rosbags typestore built from them.

The ``.msg`` files of ``src/deepsync_msgs/msg`` are the single source of truth: the core reads
the very text that ``rosidl_generate_interfaces`` compiles, so a bag written here decodes in
``ros2 bag play`` / ``ros2 topic echo`` with the built package, and nothing is duplicated in Python.
They ship inside this package too (``bag/msg``, a link to them in the checkout), so an installed
package reads and writes bags without a checkout or a ROS workspace.
"""

from __future__ import annotations

import functools
import os
from importlib.resources import files
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from .errors import MsgDefsNotFoundError

PACKAGE = "deepsync_msgs"
MSG_NAMES: tuple[str, ...] = (
    "EnvelopeSamples",
    "SyncWindow",
    "SyncWindowArray",
    "CellTiming",
    "CellTimingArray",
)
ENV_VAR = "DEEPSYNC_MSGS_DIR"


def msgtype(name: str) -> str:
    """Full ROS 2 type name of one of our messages, e.g. ``deepsync_msgs/msg/CellTiming``."""
    return f"{PACKAGE}/msg/{name}"


def _has_all(directory: Path) -> bool:
    return all((directory / f"{name}.msg").is_file() for name in MSG_NAMES)


def _shipped() -> list[Path]:
    """The definitions shipped inside this package, where it is a folder of files."""
    shipped = files(__package__) / "msg"
    return [shipped] if isinstance(shipped, Path) else []


def find_msg_dir() -> Path:
    """Directory holding the deepsync_msgs ``.msg`` files.

    Search order: ``$DEEPSYNC_MSGS_DIR`` (must be right if set: a wrong explicit setting is an
    error, not a silent fallback), ``<prefix>/share/deepsync_msgs/msg`` for each prefix of
    ``$AMENT_PREFIX_PATH`` (a sourced ROS workspace), then the copy shipped inside this package.
    """
    explicit = os.environ.get(ENV_VAR)
    if explicit:
        directory = Path(explicit).expanduser()
        if not _has_all(directory):
            missing = [n for n in MSG_NAMES if not (directory / f"{n}.msg").is_file()]
            raise MsgDefsNotFoundError(
                f"${ENV_VAR}={explicit!r} does not hold the deepsync_msgs definitions "
                f"(missing: {', '.join(f'{n}.msg' for n in missing)})"
            )
        return directory
    candidates = [
        Path(prefix) / "share" / PACKAGE / "msg"
        for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)
        if prefix
    ]
    candidates += _shipped()
    for directory in candidates:
        if _has_all(directory):
            return directory
    raise MsgDefsNotFoundError(
        "cannot find the deepsync_msgs message definitions (*.msg): source your ROS workspace "
        f"(so $AMENT_PREFIX_PATH has share/{PACKAGE}/msg) or set ${ENV_VAR} to the directory "
        "holding EnvelopeSamples.msg etc. (in a checkout: src/deepsync_msgs/msg)"
    )


def load_typestore(msg_dir: Path, older: dict[str, str] | None = None) -> Typestore:
    """ROS 2 Jazzy typestore plus our types parsed from the ``.msg`` text in ``msg_dir``;
    ``older``: message type -> the definition to take for it instead (a bag's, recorded before
    the type grew)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for name in MSG_NAMES:
        text = (msg_dir / f"{name}.msg").read_text(encoding="utf-8")
        types.update(get_types_from_msg((older or {}).get(msgtype(name), text), msgtype(name)))
    store.register(types)
    return store


@functools.lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The shared typestore (built once; ``typestore.cache_clear()`` after changing the env)."""
    return load_typestore(find_msg_dir())
