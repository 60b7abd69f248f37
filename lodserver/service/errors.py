"""The errors of the service layer that the store, the blobs and the catalogue share.

Here rather than in ``store.py`` so that ``blobs.py`` (which ``store.py``
uses) can raise them without the two modules importing each other;
``store.py`` re-exports them.
"""

from __future__ import annotations

import errno
import sqlite3

__all__ = ["StoreError", "StorageFullError", "is_disk_full"]

# PostgreSQL's SQLSTATE for "disk full" (class 53, insufficient resources).
_PG_DISK_FULL = "53100"


class StoreError(Exception):
    """A store operation cannot be done; the message says why."""


class StorageFullError(StoreError):
    """The data directory's disk (or quota) is full; nothing was changed."""


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` says the disk or the quota is full (OSError, SQLite, PostgreSQL)."""
    if isinstance(exc, OSError):
        return exc.errno in (errno.ENOSPC, errno.EDQUOT)
    if isinstance(exc, sqlite3.OperationalError):
        return (getattr(exc, "sqlite_errorcode", None) == 13      # SQLITE_FULL
                or "disk is full" in str(exc))
    return getattr(exc, "sqlstate", None) == _PG_DISK_FULL
