"""Where meshes live: the catalogue of builds and their immutable artefacts.

:class:`Store` is the interface the job runner and the API use; every method
takes keyword arguments and knows nothing of HTTP. :class:`LocalStore` is the
embedded default, needing no setup: one data directory holding

- ``catalogue.sqlite3`` : one row per mesh (status, progress, counts, error
  curve summary, failure reason, timestamps), in SQLite's WAL mode;
- ``sources/<id>.<ext>`` : the uploaded file, kept until its build is done;
- ``artefacts/<id>.pm``  : the progressive mesh, written atomically by
  ``codec.save_progressive`` and never changed afterwards;
- ``tmp/``                : scratch folders (an upload being received, a source
  being parsed), one per use, emptied every time a store opens;
- ``quarantine/``         : artefacts found corrupt, moved aside for an operator.

A mesh's life: ``queued`` (source stored) -> ``building`` -> ``ready`` (artefact
written, then the row flipped, so a ready row always has its artefact) or
``failed`` (with a reason). Opening a store after a crash or restart re-queues
the builds that were queued or building, or fails them if their source is gone,
and removes what a crash left half done: scratch folders, temporary files, and
sources or artefacts that no row names. An artefact that fails its checks when
loaded is detected once: the mesh is marked failed with the reason and the file
moved to ``quarantine/``, so later requests get that reason without a re-read.

Running out of disk space (``ENOSPC``/``EDQUOT``, or SQLite's "disk is full")
raises :class:`StorageFullError` and leaves the catalogue and files as they were.

Ids are random url-safe tokens (``secrets.token_urlsafe``), checked against
:data:`ID_PATTERN` before any path is made from them.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import re
import secrets
import shutil
import sqlite3
import tempfile
import threading
import time
from abc import ABC, abstractmethod
from collections import OrderedDict
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

from ..progressive.artefact import ArtefactError, load_progressive, save_progressive
from ..progressive.mesh import ProgressiveMesh

log = logging.getLogger(__name__)

ID_PATTERN = re.compile(r"^[A-Za-z0-9_-]{22}$")
# Loaded progressive meshes kept in memory by default: serving a level must not
# reread the file. Each holds its arrays and, once packets were asked for, its
# encoded records: 144 + 39 MB for the 1.1M-face bunny.
LOADED_CACHE_SIZE = 8


class Status(str, Enum):
    QUEUED = "queued"
    BUILDING = "building"
    READY = "ready"
    FAILED = "failed"


class StoreError(Exception):
    """A store operation cannot be done; the message says why."""


class StorageFullError(StoreError):
    """The data directory's disk (or quota) is full; nothing was changed."""


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` says the disk or the quota is full (OSError or SQLite)."""
    if isinstance(exc, OSError):
        return exc.errno in (errno.ENOSPC, errno.EDQUOT)
    if isinstance(exc, sqlite3.OperationalError):
        return (getattr(exc, "sqlite_errorcode", None) == 13      # SQLITE_FULL
                or "disk is full" in str(exc))
    return False


# The failure of a mesh whose artefact failed its checks when it was loaded.
CORRUPT_ARTEFACT = "its stored artefact is corrupt"


class UnknownMeshError(StoreError, LookupError):
    """No mesh has this id (or the id is malformed)."""

    def __init__(self, mesh_id: str):
        super().__init__(f"no mesh has the id {mesh_id!r}")
        self.mesh_id = mesh_id


class NotReadyError(StoreError):
    """The mesh exists but has no artefact: still building, or its build failed."""

    def __init__(self, record: MeshRecord):
        if record.status is Status.FAILED and (record.failure or "").startswith(CORRUPT_ARTEFACT):
            message = f"mesh {record.id} cannot be served: {record.failure}"
        elif record.status is Status.FAILED:
            message = f"mesh {record.id} failed to build: {record.failure}"
        else:
            message = (f"mesh {record.id} is not built yet (status {record.status.value}, "
                       f"progress {record.progress:.0%}); retry when its status is ready")
        super().__init__(message)
        self.record = record


@dataclass(frozen=True)
class MeshRecord:
    """One catalogue row.

    summary : ``ProgressiveMesh.summary()`` without its metadata (counts and the
    error curve) once ready, else empty. ``digest`` is the artefact's SHA-256,
    the seed of every ETag served from it.
    """

    id: str
    name: str
    status: Status
    progress: float
    file_type: str
    source_bytes: int
    options: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)
    failure: str | None = None
    digest: str | None = None
    created: float = 0.0
    updated: float = 0.0


class Store(ABC):
    """Storage of meshes: the catalogue, the sources awaiting a build, the artefacts.

    Methods raise :class:`UnknownMeshError` for an unknown or malformed id.
    Implementations must be safe to call from several threads.
    """

    @abstractmethod
    def create(self, *, name: str, source: Path, file_type: str, options: dict) -> MeshRecord:
        """Register a new mesh, queued, taking ownership of the file ``source`` (moved).

        Atomic: if it fails (:class:`StorageFullError` when the disk is full),
        no row and no stored file exist, and ``source`` is where it was.
        """

    @abstractmethod
    def scratch(self, *, prefix: str) -> Path:
        """A new empty folder for temporary files (an upload, a source to parse);
        the caller removes it, and whatever a crash leaves is removed at the next start."""

    @abstractmethod
    def get(self, *, mesh_id: str) -> MeshRecord:
        """The catalogue row of ``mesh_id``."""

    @abstractmethod
    def list(self, *, limit: int = 100, offset: int = 0) -> list[MeshRecord]:
        """Rows, newest first."""

    @abstractmethod
    def delete(self, *, mesh_id: str) -> None:
        """Forget a mesh and remove its files."""

    @abstractmethod
    def source_path(self, *, mesh_id: str) -> Path:
        """A local path of the uploaded file (for the build)."""

    @abstractmethod
    def mark_building(self, *, mesh_id: str) -> None: ...

    @abstractmethod
    def set_progress(self, *, mesh_id: str, progress: float) -> None: ...

    @abstractmethod
    def requeue(self, *, mesh_id: str) -> None:
        """Back to queued (a build interrupted by shutdown)."""

    @abstractmethod
    def mark_failed(self, *, mesh_id: str, reason: str) -> None: ...

    @abstractmethod
    def put_artefact(self, *, mesh_id: str, pm: ProgressiveMesh) -> MeshRecord:
        """Store the built artefact, mark the mesh ready and drop its source."""

    @abstractmethod
    def load(self, *, mesh_id: str) -> ProgressiveMesh:
        """The artefact of a ready mesh; :class:`NotReadyError` otherwise (also for
        an artefact found corrupt, which is then quarantined and its mesh failed)."""

    @abstractmethod
    def recover(self) -> list[str]:
        """Settle builds left unfinished by a previous process; the ids to build."""

    def close(self) -> None:
        """Release resources; the default holds none."""


_COLUMNS = ("id", "name", "status", "progress", "file_type", "source_bytes", "options", "summary",
            "failure", "digest", "created", "updated")
_SCHEMA = """
CREATE TABLE IF NOT EXISTS meshes (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    status TEXT NOT NULL,
    progress REAL NOT NULL,
    file_type TEXT NOT NULL,
    source_bytes INTEGER NOT NULL,
    options TEXT NOT NULL,
    summary TEXT NOT NULL,
    failure TEXT,
    digest TEXT,
    created REAL NOT NULL,
    updated REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS meshes_created ON meshes (created);
"""


def check_id(mesh_id: str) -> str:
    """``mesh_id`` if it has the shape of an id, else :class:`UnknownMeshError`."""
    if not isinstance(mesh_id, str) or not ID_PATTERN.match(mesh_id):
        raise UnknownMeshError(str(mesh_id)[:64])
    return mesh_id


class LocalStore(Store):
    """The embedded store: a data directory with SQLite and files (module docstring)."""

    def __init__(self, root, *, loaded_meshes: int = LOADED_CACHE_SIZE):
        if loaded_meshes < 1:
            raise ValueError(f"loaded_meshes must be at least 1, got {loaded_meshes}")
        self.loaded_meshes = loaded_meshes
        # absolute, so that the paths scrubbed from error messages are the ones used
        self.root = Path(root).absolute()
        self.sources = self.root / "sources"
        self.artefacts = self.root / "artefacts"
        self.tmp = self.root / "tmp"
        self.quarantine = self.root / "quarantine"
        for folder in (self.root, self.sources, self.artefacts, self.tmp):
            folder.mkdir(parents=True, exist_ok=True)
        # One connection shared by threads, serialised by a lock: writes are
        # small and rare next to the builds, and SQLite serialises writers anyway.
        self._lock = threading.RLock()
        self._db = sqlite3.connect(self.root / "catalogue.sqlite3", check_same_thread=False,
                                   isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(_SCHEMA)
        self._loaded: OrderedDict[str, ProgressiveMesh] = OrderedDict()
        self._loading: dict[str, threading.Lock] = {}
        self._sweep()

    def _sweep(self) -> None:
        """Remove what an interrupted process left: scratch folders (uploads cut
        off by a kill), temporary files of interrupted writes, and sources or
        artefacts no row names (a crash between a file's rename and its row).
        Only called while opening, before any request or build can be using them."""
        for stale in self.tmp.iterdir():
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale, ignore_errors=True)
            else:
                stale.unlink(missing_ok=True)
        with self._lock:
            known = {row[0] for row in self._db.execute("SELECT id FROM meshes")}
        for folder in (self.sources, self.artefacts):
            for path in folder.iterdir():
                stem = path.name.split(".")[0]
                if path.name.startswith(".") and path.name.endswith(".tmp"):
                    path.unlink(missing_ok=True)
                elif path.is_file() and ID_PATTERN.match(stem) and stem not in known:
                    log.warning("removing %s/%s: no catalogue row names it", folder.name,
                                path.name)
                    path.unlink(missing_ok=True)

    def scratch(self, *, prefix: str) -> Path:
        return Path(tempfile.mkdtemp(prefix=prefix, dir=self.tmp))

    # ---- rows -------------------------------------------------------------
    def _row(self, mesh_id: str) -> MeshRecord:
        check_id(mesh_id)
        with self._lock:
            row = self._db.execute(f"SELECT {', '.join(_COLUMNS)} FROM meshes WHERE id = ?",
                                   (mesh_id,)).fetchone()
        if row is None:
            raise UnknownMeshError(mesh_id)
        return _record(row)

    def _update(self, mesh_id: str, **values) -> None:
        check_id(mesh_id)
        values["updated"] = time.time()
        assignments = ", ".join(f"{key} = ?" for key in values)
        with self._lock:
            cursor = self._db.execute(f"UPDATE meshes SET {assignments} WHERE id = ?",
                                      (*values.values(), mesh_id))
        if cursor.rowcount == 0:
            raise UnknownMeshError(mesh_id)

    def create(self, *, name: str, source: Path, file_type: str, options: dict) -> MeshRecord:
        mesh_id = secrets.token_urlsafe(16)
        file_type = file_type.lower()
        if not re.fullmatch(r"[a-z0-9]{1,8}", file_type):
            raise StoreError(f"file type {file_type!r} is not a plain extension")
        source = Path(source)
        target = self.sources / f"{mesh_id}.{file_type}"
        # Under a temporary name first (a rename when the source is in tmp/, a copy
        # otherwise, which may run out of space): a crash mid-copy leaves a .tmp
        # file the next start removes, never a half source under a real name.
        partial = self.sources / f".{mesh_id}.{file_type}.tmp"
        try:
            shutil.move(str(source), partial)
        except BaseException as exc:
            partial.unlink(missing_ok=True)
            _raise_if_full(exc, "storing the upload")
            raise
        try:
            size = partial.stat().st_size
            os.replace(partial, target)
            now = time.time()
            row = (mesh_id, name, Status.QUEUED.value, 0.0, file_type, size,
                   json.dumps(options), "{}", None, None, now, now)
            with self._lock:
                self._db.execute(f"INSERT INTO meshes ({', '.join(_COLUMNS)}) "
                                 f"VALUES ({', '.join('?' * len(_COLUMNS))})", row)
        except BaseException as exc:
            # no row: give the file back to the caller (a rename), or drop it
            for stored in (target, partial):
                if stored.exists():
                    try:
                        os.replace(stored, source)
                    except OSError:
                        stored.unlink(missing_ok=True)
            _raise_if_full(exc, "storing the upload")
            raise
        return _record(row)

    def get(self, *, mesh_id: str) -> MeshRecord:
        return self._row(mesh_id)

    def list(self, *, limit: int = 100, offset: int = 0) -> list[MeshRecord]:
        with self._lock:
            rows = self._db.execute(f"SELECT {', '.join(_COLUMNS)} FROM meshes "
                                    "ORDER BY created DESC, id LIMIT ? OFFSET ?",
                                    (int(limit), int(offset))).fetchall()
        return [_record(row) for row in rows]

    def delete(self, *, mesh_id: str) -> None:
        record = self._row(mesh_id)
        with self._lock:
            self._db.execute("DELETE FROM meshes WHERE id = ?", (mesh_id,))
            self._loaded.pop(mesh_id, None)
        self._source(record).unlink(missing_ok=True)
        self._artefact(mesh_id).unlink(missing_ok=True)

    def source_path(self, *, mesh_id: str) -> Path:
        return self._source(self._row(mesh_id))

    def mark_building(self, *, mesh_id: str) -> None:
        self._update(mesh_id, status=Status.BUILDING.value, progress=0.0, failure=None)

    def set_progress(self, *, mesh_id: str, progress: float) -> None:
        self._update(mesh_id, progress=float(min(max(progress, 0.0), 1.0)))

    def requeue(self, *, mesh_id: str) -> None:
        self._update(mesh_id, status=Status.QUEUED.value, progress=0.0)

    def mark_failed(self, *, mesh_id: str, reason: str) -> None:
        record = self._row(mesh_id)
        self._update(mesh_id, status=Status.FAILED.value, failure=reason)
        self._source(record).unlink(missing_ok=True)

    def put_artefact(self, *, mesh_id: str, pm: ProgressiveMesh) -> MeshRecord:
        record = self._row(mesh_id)
        path = self._artefact(mesh_id)
        try:
            save_progressive(pm, path)      # atomic: nothing is left if it fails
        except BaseException as exc:
            _raise_if_full(exc, "writing the artefact")
            raise
        try:
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
            summary = {key: value for key, value in pm.summary().items() if key != "metadata"}
            summary["metadata"] = {key: pm.metadata[key] for key in ("load_report", "options")
                                   if key in pm.metadata}
            self._update(mesh_id, status=Status.READY.value, progress=1.0, failure=None,
                         summary=json.dumps(summary), digest=digest)
        except BaseException as exc:
            # deleted while building, or the row could not be written: the
            # artefact has no row to serve it
            path.unlink(missing_ok=True)
            _raise_if_full(exc, "recording the artefact")
            raise
        self._source(record).unlink(missing_ok=True)
        return self._row(mesh_id)

    def load(self, *, mesh_id: str) -> ProgressiveMesh:
        with self._lock:
            pm = self._loaded.get(mesh_id)
            if pm is not None:
                self._loaded.move_to_end(mesh_id)
                return pm
            loading = self._loading.setdefault(mesh_id, threading.Lock())
        # One load per mesh at a time: requests racing for a mesh just built share
        # one object, and with it what is cached on it (its packet records).
        with loading:
            with self._lock:
                pm = self._loaded.get(mesh_id)
            if pm is not None:
                return pm
            try:
                record = self._row(mesh_id)
                if record.status is not Status.READY:
                    raise NotReadyError(record)
                pm = self._read_artefact(record)
                with self._lock:
                    self._loaded[mesh_id] = pm
                    while len(self._loaded) > self.loaded_meshes:
                        self._loaded.popitem(last=False)
            finally:
                with self._lock:
                    self._loading.pop(mesh_id, None)
        return pm

    def _read_artefact(self, record: MeshRecord) -> ProgressiveMesh:
        """Decode a ready mesh's artefact; a missing or corrupt one fails the mesh
        (once: the row then says why, and the file is moved to ``quarantine/``)."""
        path = self._artefact(record.id)
        try:
            return load_progressive(path)
        except ArtefactError as exc:
            cause = exc.__cause__
            if isinstance(cause, OSError) and not isinstance(cause, FileNotFoundError):
                raise cause from None   # EIO, EMFILE: the server's state, not the mesh's
            detail = str(exc).replace(str(path), "the file")
            raise self._fail_artefact(record, detail) from None

    def _fail_artefact(self, record: MeshRecord, detail: str) -> NotReadyError:
        reason = f"{CORRUPT_ARTEFACT} ({detail}); delete the mesh and upload it again"
        log.error("mesh %s: %s", record.id, reason)
        path = self._artefact(record.id)
        if path.exists():
            try:
                self.quarantine.mkdir(exist_ok=True)
                os.replace(path, self.quarantine / path.name)
            except OSError:
                log.exception("could not move the artefact of mesh %s to quarantine/",
                              record.id)
        self._update(record.id, status=Status.FAILED.value, failure=reason)
        return NotReadyError(self._row(record.id))

    def recover(self) -> list[str]:
        with self._lock:
            rows = self._db.execute(f"SELECT {', '.join(_COLUMNS)} FROM meshes WHERE status IN "
                                    "(?, ?) ORDER BY created",
                                    (Status.QUEUED.value, Status.BUILDING.value)).fetchall()
        pending = []
        for record in map(_record, rows):
            if self._source(record).is_file():
                self.requeue(mesh_id=record.id)
                pending.append(record.id)
            else:
                self.mark_failed(mesh_id=record.id, reason="the uploaded file was lost before "
                                 "its build finished; upload it again")
        return pending

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # ---- paths ------------------------------------------------------------
    def _source(self, record: MeshRecord) -> Path:
        return self.sources / f"{check_id(record.id)}.{record.file_type}"

    def _artefact(self, mesh_id: str) -> Path:
        return self.artefacts / f"{check_id(mesh_id)}.pm"


def _raise_if_full(exc: BaseException, doing: str) -> None:
    """Raise a :class:`StorageFullError` (one sentence, no path) from ``exc`` if it
    says the disk is full; otherwise return, for the caller to re-raise ``exc``."""
    if is_disk_full(exc):
        raise StorageFullError(f"the server ran out of disk space while {doing}; "
                               "try again once space is freed") from exc


def _record(row) -> MeshRecord:
    values = dict(zip(_COLUMNS, row))
    values["status"] = Status(values["status"])
    values["options"] = json.loads(values["options"])
    values["summary"] = json.loads(values["summary"])
    return MeshRecord(**values)
