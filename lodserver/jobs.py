"""Background builds: a thread pool turning queued uploads into artefacts,
and a process pool parsing the files they come from.

Parsing an upload (``io.load_mesh`` and the limits) is Python holding the GIL
and, for a hostile file, possibly a lot of memory, so with a :class:`ParsePool`
it runs in separate processes: a few at a time (``workers``, with ``queue``
more waiting and the rest refused with :class:`ParserBusy`), each under an
address-space limit (``RLIMIT_AS``), so that a file cannot take the server's
memory and the server's event loop keeps its GIL. The parsed mesh comes back
pickled. A worker that runs out of memory, or dies, refuses that one file
(:class:`LimitError`) and the pool is started again.

Each build takes the mesh parsed when its upload was checked, or (a build
resumed after a restart) parses the stored source again through the same
pool, runs ``build.build`` (the numba kernel releases the GIL, so a worker
thread does not stall the server) and hands the result to the store. Progress
goes to the store a few times a second. A build that fails marks only its own
mesh failed, with the reason (running out of disk space says so); a build
cancelled by shutdown goes back to the queue for the next process
(``Store.recover``), and one cancelled by a delete is dropped.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import shutil
import sqlite3
import threading
import time
import traceback
from contextlib import contextmanager
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import numpy as np

from .build import build
from .io import LoadReport, load_mesh
from .limits import DEFAULT_MAX_TRIANGLES, LimitError, LoadLimits
from .mesh import Mesh, MeshError
from .store import MeshRecord, Store, StorageFullError, StoreError, UnknownMeshError, is_disk_full

__all__ = ["DEFAULT_MAX_TRIANGLES", "LimitError", "JobRunner", "ParsePool", "ParserBusy",
           "check_mesh_file", "warm_up"]

log = logging.getLogger(__name__)

# Seconds between progress writes: enough for a progress bar, few SQLite writes.
PROGRESS_INTERVAL = 0.5
# Address space of one parse worker by default: its imports (numpy, numba,
# trimesh) take about 0.5 GB of it before any file is read.
PARSE_MEMORY_BYTES = 4 * 2**30
# Seconds a client refused by a full parse queue is told to wait (Retry-After).
RETRY_AFTER = 5
_DISK_FULL = ("the server ran out of disk space while building; upload the mesh again once "
              "space is freed")


class ParserBusy(Exception):
    """Every parse worker is busy and the queue is full; try again after ``retry_after`` s."""

    def __init__(self, message: str, retry_after: int = RETRY_AFTER):
        super().__init__(message)
        self.retry_after = retry_after

    def __reduce__(self):
        return type(self), (str(self), self.retry_after)


class ParserClosed(ParserBusy):
    """The parse pool was shut down (the server is stopping)."""


def check_mesh_file(path, *, file_type: str, max_triangles: int, root=None,
                    limits: LoadLimits | None = None) -> tuple[Mesh, LoadReport]:
    """Load a mesh file and check it against the triangle limit.

    Parameters
    ----------
    path : path of the file; file_type : one of ``io.SUPPORTED_INPUT``.
    max_triangles : int
        Most triangles accepted after cleaning.
    root : path, optional
        The folder every file the mesh names must resolve inside (an upload's
        own folder, holding only it); None: relative to the file, unchecked.
    limits : LoadLimits, optional
        What the file may declare (checked before allocating for it).

    Returns
    -------
    (Mesh, LoadReport), as ``io.load_mesh``.

    Raises
    ------
    MeshError
        The file is not a usable mesh (the message says why).
    LimitError
        It has more than ``max_triangles`` triangles.
    """
    mesh, report = load_mesh(path, file_type=file_type, root=root, limits=limits)
    if mesh.face_count > max_triangles:
        raise LimitError(f"the mesh has {mesh.face_count} triangles; this server builds at most "
                         f"{max_triangles}")
    return mesh, report


def _start_worker(memory_bytes: int, parent: int) -> None:
    """Parse worker initialiser: cap the worker's address space, so an allocation
    past ``memory_bytes`` raises MemoryError instead of swapping the machine, and
    exit when the server (pid ``parent``) is gone: killed with -9, it cannot stop
    its workers, and one blocked writing its result to the dead server would
    wait forever."""
    import resource

    def watch_parent():
        # the server's pid, not getppid() now: it may have died during our imports
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)     # reparented: the server died; its parse is of no use to anyone

    threading.Thread(target=watch_parent, name="watch-parent", daemon=True).start()
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    if hard != resource.RLIM_INFINITY:
        memory_bytes = min(memory_bytes, hard)
    resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, hard))


def _parse_in_worker(path: str, file_type: str, root: str | None, max_triangles: int,
                     limits: LoadLimits | None) -> tuple[Mesh, LoadReport]:
    """``check_mesh_file`` in a parse worker, with every failure made a picklable
    MeshError naming ``path`` (the caller replaces it with the upload's name)."""
    try:
        return check_mesh_file(path, file_type=file_type, max_triangles=max_triangles,
                               root=root, limits=limits)
    except MeshError:
        raise
    except MemoryError:
        raise LimitError(f"cannot load {path}: reading it needs more memory than this server "
                         "allows one file") from None
    except Exception as exc:
        # a reader tripped over the file: the file's fault as far as the client
        # is concerned, a bug to look at for us (the server log gets the trace)
        traceback.print_exc()
        raise MeshError(f"cannot load {path}: the file is malformed (its reader failed with "
                        f"{type(exc).__name__})") from None


class _WorkerDied(LimitError):
    """A parse worker died (killed at its memory limit, or crashed) on a file."""


# OpenBLAS, when its threads cannot get memory under RLIMIT_AS, crashes the
# process instead of failing the call; a parse worker needs no BLAS threads.
_WORKER_ENVIRONMENT = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
                       "MKL_NUM_THREADS": "1"}
_environment_lock = threading.Lock()


@contextmanager
def _worker_environment():
    """Spawned workers inherit ``os.environ``, read before their first import (the
    parent's main module is imported first): set the variables just for the spawn."""
    with _environment_lock:
        added = [key for key in _WORKER_ENVIRONMENT if key not in os.environ]
        os.environ.update({key: _WORKER_ENVIRONMENT[key] for key in added})
        try:
            yield
        finally:
            for key in added:
                os.environ.pop(key, None)


class ParsePool:
    """Parse worker processes, bounded in number, queue and memory (module docstring).

    Parameters
    ----------
    workers : int
        Parses running at once, one process each.
    queue : int
        Parses admitted to wait for a worker; past ``workers + queue`` an
        upload is refused with :class:`ParserBusy`. Builds resumed after a
        restart are never refused, they wait.
    memory_bytes : int
        Address-space limit of each worker, in bytes.

    The processes start on the first parse (a server that never parses never
    pays for them) with the spawn method: a worker forked from a threaded
    server could inherit a lock held by another thread.
    """

    def __init__(self, *, workers: int = 1, queue: int = 4,
                 memory_bytes: int = PARSE_MEMORY_BYTES):
        self.workers, self.queue, self.memory_bytes = max(1, workers), max(0, queue), memory_bytes
        self._lock = threading.Lock()
        self._slots = threading.Semaphore(self.workers)
        self._admitted = 0
        self._executor: ProcessPoolExecutor | None = None
        self._closed = False

    @property
    def admitted(self) -> int:
        """Parses running or waiting for a worker."""
        return self._admitted

    @property
    def full(self) -> bool:
        """Whether an upload arriving now would be refused."""
        return self._admitted >= self.workers + self.queue

    def parse(self, path, *, file_type: str, root, max_triangles: int,
              limits: LoadLimits | None, admit: bool = True) -> tuple[Mesh, LoadReport]:
        """``check_mesh_file`` in a worker; see :func:`_parse_in_worker`.

        Raises ParserBusy (``admit`` and the queue is full), ParserClosed,
        LimitError (too large, or the worker ran out of memory or died) and
        MeshError (not a usable mesh).
        """
        try:
            return self.call(_parse_in_worker, str(path), file_type,
                             None if root is None else str(root), max_triangles, limits,
                             admit=admit)
        except _WorkerDied:
            raise LimitError(f"cannot load {Path(path).name}: reading it needed more memory "
                             "than this server allows one file, or crashed the reader") from None

    def call(self, function, *args, admit: bool = True):
        """Run the picklable ``function(*args)`` in a worker, waiting for a free one."""
        with self._lock:
            if self._closed:
                raise ParserClosed("the server is shutting down; try again shortly")
            if admit and self.full:
                raise ParserBusy(f"the server is already parsing {self._admitted} uploads; "
                                 f"try again in {RETRY_AFTER} seconds")
            self._admitted += 1
        try:
            with self._slots:
                executor = self._started()
                try:
                    with _worker_environment():     # a worker may be spawned here
                        future = executor.submit(function, *args)
                    return future.result()
                except BrokenProcessPool:
                    with self._lock:
                        closed = self._closed
                        if self._executor is executor:
                            self._executor = None   # the next parse starts a fresh pool
                    executor.shutdown(wait=False, cancel_futures=True)
                    if closed:
                        raise ParserClosed("the server is shutting down; try again "
                                           "shortly") from None
                    raise _WorkerDied("the parse worker ran out of memory or crashed") from None
        finally:
            with self._lock:
                self._admitted -= 1

    def _started(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._closed:
                raise ParserClosed("the server is shutting down; try again shortly")
            if self._executor is None:
                self._executor = ProcessPoolExecutor(
                    max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_start_worker, initargs=(self.memory_bytes, os.getpid()))
            return self._executor

    def shutdown(self) -> None:
        """Stop the workers now; parses in progress end with ParserClosed."""
        with self._lock:
            self._closed = True
            executor, self._executor = self._executor, None
        if executor is None:
            return
        # a parse may take a minute; a stopping server does not wait for it
        for process in list(getattr(executor, "_processes", {}).values()):
            try:
                process.terminate()
            except (OSError, AttributeError):
                pass
        executor.shutdown(wait=True, cancel_futures=True)


def warm_up() -> None:
    """Build a tiny mesh and encode its packets both ways, so numba loads (or
    compiles) every kernel before a real build or the first packet request."""
    from .packets import encode_packet, packet_between

    positions = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                      [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    pm = build(Mesh(positions, faces))
    pm.at(6)
    encode_packet(pm, pm.base_vertices, pm.vertex_count)
    encode_packet(pm, pm.vertex_count, pm.base_vertices)
    packet_between(pm, pm.base_vertices, pm.vertex_count)
    packet_between(pm, pm.vertex_count, pm.base_vertices)


def _prepare_packets(store: Store, mesh_id: str) -> None:
    """Encode every record of a ready mesh both ways, so that its first packet
    request is a slice, not a walk over every split (seconds on a million faces)."""
    from .packets import encode_records

    try:
        encode_records(store.load(mesh_id=mesh_id))
    except Exception:       # the mesh is served either way; its first packet is just slower
        log.exception("could not prepare the packets of mesh %s", mesh_id)


class JobRunner:
    """Runs builds for a store in a pool of worker threads.

    Parameters
    ----------
    store : Store
    workers : int
        Concurrent builds; each takes one core while its kernel runs.
    max_triangles : int
        Triangle limit checked again at build time (settings may have changed).
    parser : ParsePool, optional
        Where files are parsed (the server's); None parses in the calling
        thread, unbounded (a trusted caller's own files).

    ``ready`` is set once the kernels are warm (``start(warm=True)``) or at
    once without warming: until then a build would sit compiling.
    """

    def __init__(self, store: Store, *, workers: int = 1,
                 max_triangles: int = DEFAULT_MAX_TRIANGLES, parser: ParsePool | None = None):
        self.store = store
        self.max_triangles = max_triangles
        self.parser = parser
        self.ready = threading.Event()
        self.warmed_at: float | None = None
        self._pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="build")
        self._cancel: dict[str, threading.Event] = {}
        # Meshes parsed when their upload was checked, for their build to reuse:
        # a million-face file is not parsed twice. Only a few are kept (memory);
        # the others, and builds resumed after a restart, parse their file again.
        self._parsed: dict[str, tuple[Mesh, LoadReport]] = {}
        self._keep_parsed = max(1, workers) + 1
        self._lock = threading.Lock()
        self._closing = False

    def start(self, *, warm: bool = True) -> None:
        """Warm the kernels, then queue the builds a previous process left unfinished."""
        if warm:
            self._pool.submit(self._warm)
        else:
            self.ready.set()
        for mesh_id in self.store.recover():
            self.submit(mesh_id)

    def _warm(self) -> None:
        started = time.monotonic()
        try:
            warm_up()
        except Exception:       # the kernels then compile on first use; still serve
            log.exception("warming the kernels failed")
        finally:
            self.warmed_at = time.time()
            self.ready.set()
            log.info("kernels warm in %.1f s", time.monotonic() - started)

    def parse(self, source: Path, *, file_type: str, name: str, root=None,
              admit: bool = True) -> tuple[Mesh, LoadReport]:
        """Parse and check ``source`` (in the parse pool when there is one).

        Messages name ``name``, never ``source``, ``root`` or the data directory.
        """
        limits = LoadLimits(max_triangles=self.max_triangles)
        try:
            if self.parser is None:
                return check_mesh_file(source, file_type=file_type, root=root,
                                       max_triangles=self.max_triangles, limits=limits)
            return self.parser.parse(source, file_type=file_type, root=root, limits=limits,
                                     max_triangles=self.max_triangles, admit=admit)
        except MeshError as exc:
            message = scrub(str(exc), {source: name, root: "the upload",
                                       getattr(self.store, "root", None): "the server"})
            # the loader names the file by its base name: a stored source's is its id
            exc.args = (message.replace(Path(source).name, name),)
            raise

    def accept(self, *, source: Path, name: str, file_type: str, options: dict,
               root: Path | None = None) -> MeshRecord:
        """Check an uploaded file and queue its build.

        The file is loaded once here so that a file that is not a usable mesh
        is refused at once (``MeshError``, ``LimitError``, naming ``name``)
        rather than failing later in the background; ``ParserBusy`` when the
        parse queue is full. ``root`` is the folder holding only ``source``
        (the upload's own). ``source`` is moved into the store, or deleted if
        refused.
        """
        try:
            parsed = self.parse(source, file_type=file_type, name=name, root=root)
            record = self.store.create(name=name, source=source, file_type=file_type,
                                       options=options)
        finally:
            Path(source).unlink(missing_ok=True)
        with self._lock:
            if len(self._parsed) < self._keep_parsed:
                self._parsed[record.id] = parsed
        self.submit(record.id)
        return record

    def forget(self, *, mesh_id: str) -> None:
        """Delete a mesh, stopping its build if one is queued or running."""
        self.store.get(mesh_id=mesh_id)
        self.cancel(mesh_id)
        self.store.delete(mesh_id=mesh_id)

    def submit(self, mesh_id: str) -> None:
        with self._lock:
            if self._closing or mesh_id in self._cancel:
                return
            self._cancel[mesh_id] = threading.Event()
        self._pool.submit(self._run, mesh_id)

    def cancel(self, mesh_id: str) -> None:
        """Stop a queued or running build (its mesh is being deleted)."""
        with self._lock:
            self._parsed.pop(mesh_id, None)
            event = self._cancel.get(mesh_id)
        if event is not None:
            event.set()

    def shutdown(self) -> None:
        """Cancel every build and wait for the workers; unfinished builds stay queued."""
        with self._lock:
            self._closing = True
            events = list(self._cancel.values())
        for event in events:
            event.set()
        if self.parser is not None:
            self.parser.shutdown()      # a build waiting on a parse stops waiting
        self._pool.shutdown(wait=True, cancel_futures=True)

    def _run(self, mesh_id: str) -> None:
        with self._lock:
            cancel = self._cancel[mesh_id]
        settled = False   # ready or failed: nothing left to resume
        try:
            if not cancel.is_set():
                settled = self._build(mesh_id, cancel)
        except UnknownMeshError:
            settled = True  # deleted meanwhile
        except ParserClosed:
            pass            # shutting down: requeued below
        except Exception as exc:
            settled = True
            if isinstance(exc, StorageFullError) or is_disk_full(exc):
                log.error("build of mesh %s ran out of disk space", mesh_id)
                reason = _DISK_FULL
            else:
                # A bug, not bad input: log it and fail this mesh only.
                log.exception("build of mesh %s failed", mesh_id)
                reason = "internal error while building; the server log has the details"
            try:
                self.store.mark_failed(mesh_id=mesh_id, reason=reason)
            except (StoreError, OSError, sqlite3.Error):
                log.exception("could not record the failure of mesh %s", mesh_id)
        finally:
            with self._lock:
                self._cancel.pop(mesh_id, None)
            if not settled and self._closing:
                try:
                    self.store.requeue(mesh_id=mesh_id)
                except StoreError:
                    pass

    def _parse_stored(self, record: MeshRecord) -> tuple[Mesh, LoadReport]:
        """Parse a stored source again (a build resumed after a restart), by the
        upload's rule: alone in a folder of its own, linked (or copied) into one."""
        source = self.store.source_path(mesh_id=record.id)
        folder = self.store.scratch(prefix="build-")
        try:
            staged = folder / source.name
            try:
                os.link(source, staged)
            except OSError:
                shutil.copyfile(source, staged)
            return self.parse(staged, file_type=record.file_type, name=record.name,
                              root=folder, admit=False)
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def _build(self, mesh_id: str, cancel: threading.Event) -> bool:
        """Build one mesh; False if cancelled before it was ready or failed."""
        store = self.store
        record = store.get(mesh_id=mesh_id)
        store.mark_building(mesh_id=mesh_id)
        with self._lock:
            parsed = self._parsed.pop(mesh_id, None)
        try:
            mesh, report = parsed or self._parse_stored(record)
        except MeshError as exc:
            store.mark_failed(mesh_id=mesh_id, reason=str(exc))
            return True

        last = [0.0]

        def progress(done, expected):
            now = time.monotonic()
            if now - last[0] >= PROGRESS_INTERVAL:
                last[0] = now
                store.set_progress(mesh_id=mesh_id, progress=min(done / max(expected, 1), 0.99))

        options = dict(record.options)
        locked = None
        if options.pop("lock_border", False):
            from .topology import census
            locked = np.zeros(mesh.vertex_count, dtype=bool)
            locked[census(mesh.faces, mesh.vertex_count).on_boundary] = True
        try:
            pm = build(mesh, locked=locked, progress=progress, cancel=cancel, **options)
        except MeshError as exc:
            store.mark_failed(mesh_id=mesh_id, reason=str(exc))
            return True
        if cancel.is_set():
            return False  # a cut-short decimation is not the mesh's progressive mesh
        pm.metadata["source"] = record.name
        pm.metadata["load_report"] = report.as_dict()
        store.put_artefact(mesh_id=mesh_id, pm=pm)
        _prepare_packets(store, mesh_id)
        return True


def scrub(message: str, replacements: dict) -> str:
    """``message`` with each path key (as given and resolved) replaced by its value.

    Longer paths first, so a file inside a folder is named as the file.
    """
    pairs = {}
    for path, text in replacements.items():
        if path is None:
            continue
        for form in {str(path), str(Path(path).absolute()), os.path.realpath(path)}:
            if form not in ("", ".", "/"):
                pairs.setdefault(form, text)
    for form in sorted(pairs, key=len, reverse=True):
        message = message.replace(form, pairs[form])
    return message
