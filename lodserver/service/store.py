"""Where meshes live: the catalogue of builds, their sources and immutable artefacts.

:class:`Store` is the interface the job runner and the API use; every method
takes keyword arguments and knows nothing of HTTP. :class:`LocalStore` is the
store as one process sees it: its own data directory, plus a catalogue and
a blob store that default to that directory and may be shared by any number
of servers and workers (``LODSERVER_CATALOG_URL``, ``LODSERVER_STORE_URL``).

The data directory (one process's alone: it is locked while open) holds

- ``catalogue.sqlite3`` : the default catalogue (``catalog.py``: one row per
  mesh and the build queue, with leases), in SQLite's WAL mode;
- ``sources/<id>.<ext>`` : the uploaded file, kept until its build is done, and
- ``artefacts/<id>.<sha256>.pm`` : the asset (``scene/artefact.py``: a single
  mesh's progressive mesh, a scene's every part and its document in one
  file), under a key naming its own digest, written once (atomically) and never changed: both in the default
  blob store, the directory itself; with ``LODSERVER_STORE_URL`` they live there;
- ``tmp/``                : scratch folders (an upload being received, a source
  being parsed, an artefact being written), emptied every time a store opens;
- ``quarantine/``         : artefacts found corrupt, moved aside for an operator;
- ``node``                : this directory's name in lease owners, so a restart
  takes back at once the builds its previous process held.

A mesh's life: ``queued`` (source stored, then the row: a row always has its
source) -> ``building`` (claimed under a lease) -> ``ready`` (artefact stored,
then the row flipped, so a ready row always has its artefact) or ``failed``
(with a reason). A build's writes are fenced by its claim's attempt number
(:class:`LeaseLostError` once another process holds it). Opening a store
requeues the builds its node's previous process held, fails queued builds
whose source is gone, and, when the files are the data directory's own,
removes what a crash left half done: scratch folders, temporary files, and
sources or artefacts no row names. An artefact that fails its checks when
loaded is detected once: the mesh is marked failed with the reason and the
file moved to ``quarantine/``, so later requests get that reason without a re-read.

A loaded asset (``scene.asset.SceneAsset``) is kept in memory (bounded by
count and by bytes, ``loaded.py``), and served again only after the catalogue
row says the mesh is still ready with the same digest (one indexed read), so a
delete or failure on another server is seen at once.

Running out of disk space (``ENOSPC``/``EDQUOT``, SQLite's "disk is full",
PostgreSQL's 53100) raises :class:`StorageFullError` and leaves the catalogue
and files as they were.

Ids are random url-safe tokens (``secrets.token_urlsafe``), checked against
:data:`ID_PATTERN` before any path or key is made from them.
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import secrets
import shutil
import tempfile
import threading
import time
from abc import ABC, abstractmethod
from pathlib import Path

from ..io.files import write_atomic
from ..io.limits import DEFAULT_MAX_TRIANGLES
from ..progressive import ArtefactError
from ..scene.artefact import load_artefact, save_asset
from ..scene.asset import SceneAsset, artefact_summary
from .blobs import (Blobs, BlobNotFoundError, LocalBlobs, delete_later, delete_patiently,
                    open_blobs, sha256_file)
from .cache import DEFAULT_CACHE_BYTES, ArtefactCache
from .catalog import (MAX_LOST, Catalog, CatalogUnavailable, Claim, MeshRecord, Status,
                      new_owner, open_catalog)
from .errors import (LeaseLostError, SourceLostError, StorageFullError, StoreError,
                     StoreUnavailable, UnknownMeshError, is_disk_full)
from .errors import raise_if_full as _raise_if_full
from .loaded import LOADED_BYTES_PER_TRIANGLE, LoadedArtefacts

__all__ = ["CORRUPT_ARTEFACT", "ID_PATTERN", "LOADED_BYTES", "LOADED_BYTES_PER_TRIANGLE",
           "LOADED_CACHE_SIZE", "Claim", "LeaseLostError",
           "LocalStore", "MeshRecord", "NotReadyError", "SourceLostError", "Status",
           "StorageFullError", "Store", "StoreError", "UnknownMeshError", "check_id",
           "is_disk_full"]

log = logging.getLogger(__name__)

ID_PATTERN = re.compile(r"^[A-Za-z0-9_-]{22}$")
# Loaded progressive meshes and scenes kept in memory by default: serving a level
# must not reread the file. Each holds its arrays and, once packets were asked
# for, its encoded records; what bounds them is their bytes (``loaded.py``): by
# default room for one mesh at the default triangle limit.
LOADED_CACHE_SIZE = 8
LOADED_BYTES = LOADED_BYTES_PER_TRIANGLE * DEFAULT_MAX_TRIANGLES

# The failure of a mesh whose artefact failed its checks when it was loaded.
CORRUPT_ARTEFACT = "its stored artefact is corrupt"
_ABANDONED = (f"its build stopped {MAX_LOST} times with the process building it (killed, or "
              "out of memory), so it is not tried again; upload it again, perhaps smaller")


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


class Store(ABC):
    """Storage of meshes: the catalogue and build queue, the sources, the artefacts.

    Methods raise :class:`UnknownMeshError` for an unknown or malformed id.
    The build methods take the ``attempt`` of the caller's :class:`Claim`: with
    it, a write only happens while that claim is current (else
    :class:`LeaseLostError`); without it (tests, tools) it happens regardless.
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
        """Forget a mesh and remove its files (a build running anywhere loses its claim)."""

    @abstractmethod
    def stage_source(self, *, mesh_id: str, folder: Path) -> Path:
        """The uploaded file as a file in ``folder`` (linked, copied or fetched), for a build."""

    @abstractmethod
    def claim(self, *, lease_seconds: float, mesh_id: str | None = None) -> Claim | None:
        """Take the oldest queued build (or only ``mesh_id``), or one whose lease ran
        out, under a lease of ``lease_seconds``; None when there is none."""

    @abstractmethod
    def renew(self, *, claim: Claim, lease_seconds: float) -> bool:
        """Extend ``claim``'s lease; False once it is no longer current."""

    @abstractmethod
    def mark_building(self, *, mesh_id: str) -> None:
        """Building, without a lease (claimable by anyone): for tools and tests."""

    @abstractmethod
    def set_progress(self, *, mesh_id: str, progress: float, attempt: int | None = None) -> None:
        ...

    @abstractmethod
    def requeue(self, *, mesh_id: str, attempt: int | None = None) -> None:
        """Back to queued (a build interrupted by shutdown), its lease given up."""

    @abstractmethod
    def mark_failed(self, *, mesh_id: str, reason: str, attempt: int | None = None) -> None: ...

    @abstractmethod
    def put_artefact(self, *, mesh_id: str, asset: SceneAsset,
                     attempt: int | None = None, patience: float = 0.0) -> MeshRecord:
        """Store the built asset as one artefact (``scene.artefact``: a single mesh's
        ``.pm`` file, a scene's parts and document in one file), mark the mesh
        ready and drop its source. While the catalogue cannot be reached, marking it ready is
        tried again for up to ``patience`` seconds (a builder gives its lease)."""

    @abstractmethod
    def load(self, *, mesh_id: str) -> SceneAsset:
        """The asset of a ready mesh; :class:`NotReadyError`
        otherwise (also for an artefact found corrupt, which is then quarantined and
        its mesh failed)."""

    @abstractmethod
    def recover(self) -> list[str]:
        """Settle builds left unfinished by this node's previous process; the queued ids."""

    def queue_position(self, *, mesh_id: str) -> int | None:
        """While ``mesh_id`` is queued, how many queued meshes were created before it
        (builds are claimed oldest first: 0 is next); None when it is not queued.
        This default pages through :meth:`list`; a store with a catalogue asks it."""
        record = self.get(mesh_id=mesh_id)
        if record.status is not Status.QUEUED:
            return None
        ahead, offset = 0, 0
        while page := self.list(limit=1000, offset=offset):
            ahead += sum(other.status is Status.QUEUED and (other.created, other.id)
                         < (record.created, record.id) for other in page)
            offset += len(page)
        return ahead

    def held_source_bytes(self) -> int:
        """Bytes of the sources kept for builds not yet done (queued or building): what
        the queue holds on disk or in the object store. This default pages through
        :meth:`list`; a store with a catalogue asks it."""
        held, offset = 0, 0
        while page := self.list(limit=1000, offset=offset):
            held += sum(record.source_bytes for record in page
                        if record.status in (Status.QUEUED, Status.BUILDING))
            offset += len(page)
        return held

    def close(self) -> None:
        """Release resources; the default holds none."""


def check_id(mesh_id: str) -> str:
    """``mesh_id`` if it has the shape of an id, else :class:`UnknownMeshError`."""
    if not isinstance(mesh_id, str) or not ID_PATTERN.match(mesh_id):
        raise UnknownMeshError(str(mesh_id)[:64])
    return mesh_id


def source_key(record: MeshRecord) -> str:
    return f"sources/{check_id(record.id)}.{record.file_type}"


def artefact_key(mesh_id: str, digest: str) -> str:
    """The key of a mesh's artefact: its id and the SHA-256 of its bytes. It is
    content-addressed within the mesh (a cached copy can never be stale), yet no
    two meshes share one, so deleting a mesh deletes its artefact with no count
    of references (identical uploads would otherwise race a delete)."""
    if not re.fullmatch(r"[0-9a-f]{64}", digest or ""):
        raise StoreError(f"mesh {mesh_id} has no artefact digest")
    return f"artefacts/{check_id(mesh_id)}.{digest}.pm"


class LocalStore(Store):
    """A data directory of this process, with a catalogue and blobs (module docstring).

    Parameters
    ----------
    root : path
        The data directory; created if absent; locked while the store is open
        (:class:`StoreError` if another process has it).
    loaded_meshes : int
        Most progressive meshes and scenes kept in memory.
    loaded_bytes : int
        Most bytes of them kept (``loaded.LoadedArtefacts``).
    catalog : Catalog or str, optional
        The catalogue or its URL (``catalog.open_catalog``); default SQLite in ``root``.
    blobs : Blobs or str, optional
        The blob store or its URL (``blobs.open_blobs``); default ``root`` itself.
    cache_bytes : int
        Remote blobs only: bytes of fetched artefacts kept under ``root/cache``.
    """

    def __init__(self, root, *, loaded_meshes: int = LOADED_CACHE_SIZE,
                 loaded_bytes: int = LOADED_BYTES,
                 catalog: Catalog | str | None = None, blobs: Blobs | str | None = None,
                 cache_bytes: int = DEFAULT_CACHE_BYTES):
        # id -> the artefact at a digest: served again only while the row has it
        self._loaded = LoadedArtefacts(count=loaded_meshes, nbytes=loaded_bytes)
        self.loaded_meshes, self.loaded_bytes = loaded_meshes, loaded_bytes
        # absolute, so that the paths scrubbed from error messages are the ones used
        self.root = Path(root).absolute()
        self.tmp = self.root / "tmp"
        self.quarantine = self.root / "quarantine"
        for folder in (self.root, self.tmp):
            folder.mkdir(parents=True, exist_ok=True)
        self._lock_file = _lock_directory(self.root)
        try:
            self.node = _node_name(self.root)
            self.owner = new_owner(self.node)
            # the files are the data directory's own unless a store URL is given
            self.shared_files = blobs is not None
            self.blobs = blobs if isinstance(blobs, Blobs) else open_blobs(blobs or self.root)
            self.local_files = isinstance(self.blobs, LocalBlobs)
            if self.local_files:
                self.sources = Path(self.blobs.root) / "sources"
                self.artefacts = Path(self.blobs.root) / "artefacts"
                for folder in (self.sources, self.artefacts):
                    folder.mkdir(parents=True, exist_ok=True)
            self.catalog = (catalog if isinstance(catalog, Catalog)
                            else open_catalog(catalog, data_dir=self.root))
        except BaseException:
            self._lock_file.close()
            raise
        # artefacts read from a remote store, kept on this machine (bounded)
        self._cache = None if self.local_files else ArtefactCache(self.root / "cache",
                                                                  cache_bytes)
        self._lock = threading.RLock()
        self._loading: dict[str, threading.Lock] = {}
        self._sweep()

    def _sweep(self) -> None:
        """Remove what an interrupted process left: scratch folders (uploads cut
        off by a kill), and, when the files are this directory's own, temporary
        files of interrupted writes and sources or artefacts no row names (a
        crash between a file's rename and its row). Only called while opening,
        before any request or build of this process can be using them; files in a
        shared store are never swept here (another server may be mid-write)."""
        for stale in self.tmp.iterdir():
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale, ignore_errors=True)
            else:
                stale.unlink(missing_ok=True)
        if self.shared_files or not self.local_files:
            return
        rows = {mesh_id: (status, digest) for mesh_id, _, status, digest
                in self.catalog.artefacts()}
        for folder in (self.sources, self.artefacts):
            for path in folder.iterdir():
                stem, *rest = path.name.split(".")
                if path.name.startswith(".") and path.name.endswith(".tmp"):
                    path.unlink(missing_ok=True)
                elif not (path.is_file() and ID_PATTERN.match(stem)):
                    continue
                elif stem not in rows:
                    log.warning("removing %s/%s: no catalogue row names it", folder.name,
                                path.name)
                    path.unlink(missing_ok=True)
                elif folder is self.artefacts:
                    self._sweep_artefact(path, stem, rest, *rows[stem])

    def _sweep_artefact(self, path: Path, mesh_id: str, rest: list[str], status: str,
                        digest: str | None) -> None:
        if rest == ["pm"] and status == Status.READY.value and digest:
            # a data directory from before keys named the digest
            os.replace(path, self.artefacts / Path(artefact_key(mesh_id, digest)).name)
        elif rest != [digest, "pm"]:
            log.warning("removing artefacts/%s: not the artefact its row names", path.name)
            path.unlink(missing_ok=True)

    def scratch(self, *, prefix: str) -> Path:
        return Path(tempfile.mkdtemp(prefix=prefix, dir=self.tmp))

    # ---- rows -------------------------------------------------------------
    def _row(self, mesh_id: str) -> MeshRecord:
        record = self.catalog.get(mesh_id=check_id(mesh_id))
        if record is None:
            raise UnknownMeshError(mesh_id)
        return record

    def _update(self, mesh_id: str, attempt: int | None = None, **values) -> MeshRecord:
        record = self.catalog.update(mesh_id=check_id(mesh_id), values=values,
                                     updated=time.time(), attempt=attempt)
        if record is None:
            if attempt is None or self.catalog.get(mesh_id=mesh_id) is None:
                raise UnknownMeshError(mesh_id)
            raise LeaseLostError(mesh_id)
        return record

    def create(self, *, name: str, source: Path, file_type: str, options: dict) -> MeshRecord:
        mesh_id = secrets.token_urlsafe(16)
        file_type = file_type.lower()
        if not re.fullmatch(r"[a-z0-9]{1,8}", file_type):
            raise StoreError(f"file type {file_type!r} is not a plain extension")
        source = Path(source)
        now = time.time()
        record = MeshRecord(id=mesh_id, name=name, status=Status.QUEUED, progress=0.0,
                            file_type=file_type, source_bytes=source.stat().st_size,
                            options=dict(options), created=now, updated=now)
        key = source_key(record)
        if self.local_files:
            stored = self._store_local_source(source, key)
        else:
            try:
                self.blobs.put_file(key, source)        # a copy: `source` stays until the row
            except BaseException as exc:
                if isinstance(exc, StoreUnavailable):   # it may be stored, answer lost
                    delete_later(self.blobs, key)
                _raise_if_full(exc, "storing the upload")
                raise
        try:
            self.catalog.insert(record)
        except BaseException as exc:
            # no row: give the file back to the caller (a rename), or drop it
            if self.local_files:
                try:
                    os.replace(stored, source)
                except OSError:
                    stored.unlink(missing_ok=True)
            else:
                self.blobs.delete(key)
            _raise_if_full(exc, "storing the upload")
            raise
        if not self.local_files:
            source.unlink(missing_ok=True)
        return record

    def _store_local_source(self, source: Path, key: str) -> Path:
        """Move ``source`` to ``key`` of the local blobs, through a temporary name
        (a rename when the source is in tmp/, a copy otherwise, which may run out of
        space): a crash mid-copy leaves a .tmp file the next start removes, never a
        half source under a real name."""
        target = self._local(key)
        partial = target.with_name(f".{target.name}.tmp")
        try:
            shutil.move(str(source), partial)
            os.replace(partial, target)
        except BaseException as exc:
            if partial.exists() and not source.exists():
                os.replace(partial, source)
            partial.unlink(missing_ok=True)
            _raise_if_full(exc, "storing the upload")
            raise
        return target

    def get(self, *, mesh_id: str) -> MeshRecord:
        return self._row(mesh_id)

    def list(self, *, limit: int = 100, offset: int = 0) -> list[MeshRecord]:
        return self.catalog.list(limit=limit, offset=offset)

    def delete(self, *, mesh_id: str) -> None:
        record = self.catalog.delete(mesh_id=check_id(mesh_id))
        if record is None:
            raise UnknownMeshError(mesh_id)
        self._loaded.pop(mesh_id)
        # the row is gone first: a server loading this mesh now finds no row, never
        # a row without its files. The mesh is gone whatever happens to its files.
        keys = [source_key(record)]
        if record.digest:
            keys.append(artefact_key(mesh_id, record.digest))
        for key in keys:
            try:
                self.blobs.delete(key)
            except StoreError as exc:
                log.warning("mesh %s deleted, but not its object %s: %s", mesh_id, key, exc)

    def source_path(self, *, mesh_id: str) -> Path:
        """Where the uploaded file of ``mesh_id`` is kept (local files only)."""
        if not self.local_files:
            raise StoreError("the sources are in a remote store; use stage_source")
        return self._local(source_key(self._row(mesh_id)))

    def stage_source(self, *, mesh_id: str, folder: Path) -> Path:
        key = source_key(self._row(mesh_id))
        staged = Path(folder) / key.split("/")[-1]
        local = self.blobs.local_path(key)
        if local is not None:
            try:
                os.link(local, staged)
                return staged
            except OSError:
                pass        # another file system: a copy
        try:
            self.blobs.get_file(key, staged)
        except BlobNotFoundError:
            raise SourceLostError() from None
        return staged

    # ---- the queue ---------------------------------------------------------
    def claim(self, *, lease_seconds: float, mesh_id: str | None = None) -> Claim | None:
        now = time.time()
        for record in self.catalog.abandon(max_lost=MAX_LOST, reason=_ABANDONED, updated=now):
            log.error("mesh %s: %s", record.id, _ABANDONED)
            self.blobs.delete(source_key(record))
        return self.catalog.claim(owner=self.owner, lease_seconds=lease_seconds, updated=now,
                                  mesh_id=None if mesh_id is None else check_id(mesh_id))

    def renew(self, *, claim: Claim, lease_seconds: float) -> bool:
        return self.catalog.renew(claim=claim, lease_seconds=lease_seconds)

    def mark_building(self, *, mesh_id: str) -> None:
        self._update(mesh_id, status=Status.BUILDING.value, progress=0.0, failure=None,
                     lease_owner=None, lease_until=None)

    def set_progress(self, *, mesh_id: str, progress: float, attempt: int | None = None) -> None:
        self._update(mesh_id, attempt, progress=float(min(max(progress, 0.0), 1.0)))

    def requeue(self, *, mesh_id: str, attempt: int | None = None) -> None:
        self._update(mesh_id, attempt, status=Status.QUEUED.value, progress=0.0,
                     lease_owner=None, lease_until=None)

    def mark_failed(self, *, mesh_id: str, reason: str, attempt: int | None = None) -> None:
        record = self._update(mesh_id, attempt, status=Status.FAILED.value, failure=reason,
                              lease_owner=None, lease_until=None)
        self.blobs.delete(source_key(record))

    def put_artefact(self, *, mesh_id: str, asset: SceneAsset,
                     attempt: int | None = None, patience: float = 0.0) -> MeshRecord:
        record = self._row(mesh_id)
        folder = self.scratch(prefix="artefact-")
        try:
            path = folder / "artefact.pm"
            try:
                # atomic: nothing is left if it fails
                save_asset(asset, path)
                digest = sha256_file(path)
                key = artefact_key(mesh_id, digest)
                self.blobs.put_file(key, path, move=True)
            except BaseException as exc:
                _raise_if_full(exc, "writing the artefact")
                raise
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        summary = artefact_summary(asset)
        try:
            ready = self._mark_ready(mesh_id, attempt, patience, status=Status.READY.value,
                                     progress=1.0, failure=None, summary=summary, digest=digest,
                                     lease_owner=None, lease_until=None)
        except (LeaseLostError, CatalogUnavailable):
            # Another process holds the build now and may be storing this very key
            # (builds are deterministic); or the catalogue stayed out of reach and
            # the row may name the key (a commit whose answer was lost). Either
            # way the object is left: the row, or the next build, names it.
            raise
        except BaseException as exc:
            # deleted while building (no row can ever name this key again), or the
            # row could not be written: the artefact has no row to serve it
            self.blobs.delete(key)
            _raise_if_full(exc, "recording the artefact")
            raise
        # the row no longer names the source: nothing else would remove it
        delete_patiently(self.blobs, source_key(record), patience=max(patience, 1.0))
        return ready

    def _mark_ready(self, mesh_id: str, attempt: int | None, patience: float,
                    **values) -> MeshRecord:
        """The fenced write that makes a build done, tried again with a growing pause
        for up to ``patience`` seconds while the catalogue is unreachable (restarted,
        failed over): the artefact is stored already, and giving up throws the
        build away. A write refused after an attempt whose answer was lost is the
        done row when that row names this very artefact (the lost answer was a
        commit), not a lost lease."""
        deadline = time.monotonic() + patience
        pause, unsure = 0.05, False
        while True:
            try:
                return self._update(mesh_id, attempt, **values)
            except LeaseLostError:
                if unsure:
                    record = self._row(mesh_id)
                    if record.status is Status.READY and record.digest == values["digest"]:
                        return record
                raise
            except CatalogUnavailable as exc:
                unsure = True
                if time.monotonic() + pause > deadline:
                    raise
                log.warning("mesh %s is built but cannot be marked ready yet (trying again): "
                            "%s", mesh_id, exc)
                time.sleep(pause)
                pause = min(2 * pause, 2.0)

    # ---- loading -------------------------------------------------------------
    def load(self, *, mesh_id: str) -> SceneAsset:
        # The row first, every time (one indexed read): another server may have
        # deleted or failed the mesh since it was loaded here.
        record = self._row(mesh_id)
        if record.status is not Status.READY:
            self._loaded.pop(mesh_id)
            raise NotReadyError(record)
        cached = self._loaded.get(mesh_id, record.digest)
        if cached is not None:
            return cached
        with self._lock:
            loading = self._loading.setdefault(mesh_id, threading.Lock())
        # One load per mesh at a time: requests racing for a mesh just built share
        # one object, and with it what is cached on it (its packet records).
        with loading:
            try:
                asset = self._loaded.get(mesh_id, record.digest)
                if asset is None:
                    asset = self._read_artefact(record)
                    self._loaded.put(mesh_id, record.digest, asset)
            finally:
                with self._lock:
                    self._loading.pop(mesh_id, None)
        return asset

    def _read_artefact(self, record: MeshRecord) -> SceneAsset:
        """Decode a ready mesh's artefact; a missing or corrupt one fails the mesh
        (once: the row then says why, and the file is moved to ``quarantine/``)."""
        key = artefact_key(record.id, record.digest)
        if self.local_files:
            return self._decode(record, key, self._local(key))
        try:
            # held in place while read: another request's fetch cannot evict it
            with self._cache.lease(key, lambda dest: self.blobs.get_file(key, dest)) as path:
                return self._decode(record, key, path)
        except BlobNotFoundError:
            raise self._fail_artefact(record, key, "it is missing from the store") from None

    def _decode(self, record: MeshRecord, key: str, path: Path) -> SceneAsset:
        try:
            return load_artefact(path)
        except ArtefactError as exc:
            cause = exc.__cause__
            if isinstance(cause, OSError) and not isinstance(cause, FileNotFoundError):
                raise cause from None   # EIO, EMFILE: the server's state, not the mesh's
            detail = str(exc).replace(str(path), "the file")
            raise self._fail_artefact(record, key, detail, path) from None

    def _fail_artefact(self, record: MeshRecord, key: str, detail: str,
                       path: Path | None = None) -> NotReadyError:
        reason = f"{CORRUPT_ARTEFACT} ({detail}); delete the mesh and upload it again"
        log.error("mesh %s: %s", record.id, reason)
        if path is not None and path.exists():
            try:
                self.quarantine.mkdir(exist_ok=True)
                if self.local_files:
                    os.replace(path, self.quarantine / Path(key).name)
                else:
                    # the store's object stays (the row still names it, for an
                    # operator); this server's copy is set aside and forgotten
                    shutil.copyfile(path, self.quarantine / Path(key).name)
                    self._cache.discard(key)
            except OSError:
                log.exception("could not move the artefact of mesh %s to quarantine/",
                              record.id)
        self._update(record.id, status=Status.FAILED.value, failure=reason)
        return NotReadyError(self._row(record.id))

    def recover(self) -> list[str]:
        requeued = self.catalog.recover(node=self.node, updated=time.time())
        if requeued:
            log.info("requeued %d build(s) left by this node's previous process", len(requeued))
        pending = []
        for record in self.catalog.pending():
            if self.blobs.exists(source_key(record)):
                pending.append(record.id)
            else:
                self.mark_failed(mesh_id=record.id, reason=str(SourceLostError()))
        return pending

    def queue_position(self, *, mesh_id: str) -> int | None:
        record = self._row(mesh_id)
        return self.catalog.queued_before(record) if record.status is Status.QUEUED else None

    def held_source_bytes(self) -> int:
        return self.catalog.held_source_bytes()

    def close(self) -> None:
        self.catalog.close()
        self._lock_file.close()         # releases the data directory's lock

    # ---- paths ------------------------------------------------------------
    def _local(self, key: str) -> Path:
        return Path(self.blobs.root, *key.split("/"))


def _lock_directory(root: Path):
    """An exclusive lock on ``root`` held while the returned file is open: two
    processes sharing one data directory would sweep each other's scratch files."""
    file = open(root / "lodserver.lock", "a+b")
    try:
        fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        file.close()
        raise StoreError("the data directory is in use by another lodserver process; give "
                         "each server and worker its own LODSERVER_DATA_DIR (they share "
                         "LODSERVER_STORE_URL and LODSERVER_CATALOG_URL)") from None
    return file


def _node_name(root: Path) -> str:
    """The data directory's lasting name in lease owners (made once)."""
    path = root / "node"
    try:
        name = path.read_text().strip()
        if re.fullmatch(r"[A-Za-z0-9_-]{8,64}", name):
            return name
    except FileNotFoundError:
        pass
    name = secrets.token_urlsafe(9)
    write_atomic(path, name.encode())
    return name

