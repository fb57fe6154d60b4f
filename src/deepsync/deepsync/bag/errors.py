"""The one exception type bag IO raises, so callers catch bag problems without knowing rosbags."""

from __future__ import annotations


class BagError(ValueError):
    """A bag cannot be read or written; the message names the path and the cause."""


class BagExistsError(BagError, FileExistsError):
    """The output bag directory exists already and overwriting was not requested."""


class MsgDefsNotFoundError(BagError, FileNotFoundError):
    """The deepsync_msgs ``.msg`` files are nowhere to be found (workspace not sourced?)."""
