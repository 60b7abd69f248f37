"""Where meshes live: the catalogue of builds and their immutable artefacts.

:class:`Store` is the interface the job runner and the API use; every method
takes keyword arguments and knows nothing of HTTP. :class:`LocalStore` is the
embedded default, needing no setup: one data directory holding

- ``catalogue.sqlite3`` : one row per mesh (status, progress, counts, error
  curve summary, failure reason, timestamps), in SQLite's WAL mode;
- ``sources/<id>.<ext>`` : the uploaded file, kept until its build is done;
- ``artefacts/<id>.pm``  : the progressive mesh, written atomically by
  ``codec.save_progressive`` and never changed afterwards.

A mesh's life: ``queued`` (source stored) -> ``building`` -> ``ready`` (artefact
written, then the row flipped, so a ready row always has its artefact) or
``failed`` (with a reason). Opening a store after a crash or restart re-queues
the builds that were queued or building, or fails them if their source is gone.

Ids are random url-safe tokens (``secrets.token_urlsafe``), checked against
:data:`ID_PATTERN` before any path is made from them.
"""

from __future__ import annotations

import hashlib
import json
import re
import secrets
import shutil
import sqlite3
import threading
import time
from abc import ABC, abstractmethod
from collections import OrderedDict
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

from .codec import load_progressive, save_progressive
from .progressive import ProgressiveMesh

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


class UnknownMeshError(StoreError, LookupError):
    """No mesh has this id (or the id is malformed)."""

    def __init__(self, mesh_id: str):
        super().__init__(f"no mesh has the id {mesh_id!r}")
        self.mesh_id = mesh_id


class NotReadyError(StoreError):
    """The mesh exists but has no artefact: still building, or its build failed."""

    def __init__(self, record: MeshRecord):
        if record.status is Status.FAILED:
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
        """Register a new mesh, queued, taking ownership of the file ``source`` (moved)."""

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
        """The artefact of a ready mesh; :class:`NotReadyError` otherwise."""

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
        self.root = Path(root)
        self.sources = self.root / "sources"
        self.artefacts = self.root / "artefacts"
        for folder in (self.root, self.sources, self.artefacts):
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
        # Temporary files of writes interrupted by a crash are never served; drop them.
        for folder in (self.sources, self.artefacts):
            for stale in folder.glob(".*.tmp"):
                stale.unlink(missing_ok=True)

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
        target = self.sources / f"{mesh_id}.{file_type}"
        shutil.move(str(source), target)
        now = time.time()
        row = (mesh_id, name, Status.QUEUED.value, 0.0, file_type, target.stat().st_size,
               json.dumps(options), "{}", None, None, now, now)
        with self._lock:
            self._db.execute(f"INSERT INTO meshes ({', '.join(_COLUMNS)}) "
                             f"VALUES ({', '.join('?' * len(_COLUMNS))})", row)
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
        save_progressive(pm, path)
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        summary = {key: value for key, value in pm.summary().items() if key != "metadata"}
        summary["metadata"] = {key: pm.metadata[key] for key in ("load_report", "options")
                               if key in pm.metadata}
        try:
            self._update(mesh_id, status=Status.READY.value, progress=1.0, failure=None,
                         summary=json.dumps(summary), digest=digest)
        except UnknownMeshError:
            # deleted while building: the artefact has no row to serve it
            path.unlink(missing_ok=True)
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
                pm = load_progressive(self._artefact(mesh_id))
                with self._lock:
                    self._loaded[mesh_id] = pm
                    while len(self._loaded) > self.loaded_meshes:
                        self._loaded.popitem(last=False)
            finally:
                with self._lock:
                    self._loading.pop(mesh_id, None)
        return pm

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


def _record(row) -> MeshRecord:
    values = dict(zip(_COLUMNS, row))
    values["status"] = Status(values["status"])
    values["options"] = json.loads(values["options"])
    values["summary"] = json.loads(values["summary"])
    return MeshRecord(**values)
