"""The errors of the service layer that the store, the blobs and the catalogue share.

Here rather than in ``store.py`` so that ``blobs.py`` (which ``store.py``
uses) can raise them without the two modules importing each other;
``store.py`` re-exports them.
"""

from __future__ import annotations

import errno
import sqlite3

__all__ = ["StoreError", "StoreUnavailable", "StorageFullError", "is_disk_full", "raise_if_full"]

# PostgreSQL's SQLSTATE for "disk full" (class 53, insufficient resources).
_PG_DISK_FULL = "53100"


class StoreError(Exception):
    """A store operation cannot be done; the message says why."""


class StoreUnavailable(StoreError, ConnectionError):
    """The object store cannot be reached now (refused, reset, timed out): the
    server's dependency, not the request's. A ``ConnectionError``, like the
    catalogue's ``CatalogUnavailable``, so that callers treating an outage as
    "try again later" see both; the message names no endpoint."""

    retry_after = 10


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


def raise_if_full(exc: BaseException, doing: str) -> None:
    """Raise a :class:`StorageFullError` (one sentence, no path) from ``exc`` if it
    says the disk is full; otherwise return, for the caller to re-raise ``exc``."""
    if isinstance(exc, StorageFullError):
        raise exc
    if is_disk_full(exc):
        raise StorageFullError(f"the server ran out of disk space while {doing}; "
                               "try again once space is freed") from exc


class UnknownMeshError(StoreError, LookupError):
    """No mesh has this id (or the id is malformed)."""

    def __init__(self, mesh_id: str):
        super().__init__(f"no mesh has the id {mesh_id!r}")
        self.mesh_id = mesh_id


class LeaseLostError(StoreError):
    """A build's write was refused: its claim is no longer current (another process
    took the build over after the lease ran out, or it was settled)."""

    def __init__(self, mesh_id: str):
        super().__init__(f"the build of mesh {mesh_id} is no longer held by this process")
        self.mesh_id = mesh_id


class SourceLostError(StoreError):
    """The uploaded file of a queued build is gone from the store."""

    def __init__(self):
        super().__init__("the uploaded file was lost before its build finished; upload it "
                         "again")
