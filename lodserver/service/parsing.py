"""Parsing uploads in worker processes, a few at a time, each under a memory limit.

Parsing a file (``io.load_mesh`` and the limits) is Python holding the GIL
and, for a hostile file, possibly a lot of memory, so a :class:`ParsePool`
runs it in separate processes: a few at a time (``workers``, with ``queue``
more waiting and the rest refused with :class:`ParserBusy`), each under an
address-space limit (``RLIMIT_AS``), so that a file cannot take the server's
memory and the server's event loop keeps its GIL. The parsed mesh comes back
pickled. A worker that runs out of memory, or dies, refuses that one file
(:class:`LimitError`) and the pool is started again; so does one whose result
is too large to send back (more than half the worker's memory once pickled), or
that fails to send it.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import shutil
import tempfile
import threading
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from ..io import LoadReport, load_mesh
from ..io.fileset import DEFAULT_SET_LIMITS, FileSetLimits, open_set
from ..io.limits import LimitError, LoadLimits, OutOfMemory
from ..mesh import Mesh, MeshError

if TYPE_CHECKING:       # annotations only: the scene reader is imported when needed
    from ..io.scene import Scene
    from ..scene.load import SceneReport

# Address space of one parse worker by default: its imports (numpy, numba,
# trimesh) take about 0.5 GB of it before any file is read.
PARSE_MEMORY_BYTES = 4 * 2**30
# Seconds a client refused by a full parse queue is told to wait (Retry-After).
RETRY_AFTER = 5


class ParserBusy(Exception):
    """Every parse worker is busy and the queue is full; try again after ``retry_after`` s."""

    def __init__(self, message: str, retry_after: int = RETRY_AFTER):
        super().__init__(message)
        self.retry_after = retry_after

    def __reduce__(self):
        return type(self), (str(self), self.retry_after)


class ParserClosed(ParserBusy):
    """The parse pool was shut down (the server is stopping)."""


# The type of a stored set of files (io.fileset): one zip holding the mesh file
# and what it names, unpacked at parse time.
SET_TYPE = "zip"


def check_mesh_file(path, *, file_type: str, max_triangles: int, root=None,
                    limits: LoadLimits | None = None,
                    set_limits: FileSetLimits | None = None,
                    scenes: bool = False
                    ) -> tuple[Mesh | Scene, LoadReport | SceneReport]:
    """Load a mesh file (or a set of files) and check it against the triangle limit.

    Parameters
    ----------
    path : path of the file; file_type : one of ``io.SUPPORTED_INPUT``, or
        :data:`SET_TYPE` for a set's archive (``io.fileset.pack_set``).
    max_triangles : int
        Most triangles accepted after cleaning.
    root : path, optional
        The folder every file the mesh names must resolve inside (an upload's
        own folder, holding only it); None: relative to the file, unchecked.
        A set's main file is extracted into a new folder inside ``root`` (else
        beside the archive), which is then the root of its references: they
        resolve only inside the set, and each file is extracted when one names
        it (``io.fileset.open_set``). The folder is removed afterwards.
    limits : LoadLimits, optional
        What the file may declare (checked before allocating for it).
    set_limits : FileSetLimits, optional
        What a set's archive may hold (default ``FileSetLimits()``).
    scenes : bool
        Keep a glTF that is a scene (``scene.load.scene_reason``) as one: the
        result is then ``(io.scene.Scene, scene.load.SceneReport)``.

    Returns
    -------
    (Mesh, LoadReport), as ``io.load_mesh``; or (Scene, SceneReport) with ``scenes``.

    Raises
    ------
    MeshError
        The file is not a usable mesh (the message says why).
    LimitError
        It has more than ``max_triangles`` triangles.
    """
    if file_type == SET_TYPE:
        unpacked = Path(tempfile.mkdtemp(prefix="set-", dir=root or Path(path).parent))
        try:
            with open_set(path, unpacked, set_limits or DEFAULT_SET_LIMITS) as main:
                return check_mesh_file(main, file_type=main.suffix.lower().lstrip("."),
                                       max_triangles=max_triangles, root=unpacked,
                                       limits=limits, scenes=scenes)
        finally:
            shutil.rmtree(unpacked, ignore_errors=True)
    if scenes and file_type in ("gltf", "glb"):
        from ..scene.load import read_scene_upload
        scene = read_scene_upload(path, root=root, limits=limits,
                                  max_triangles=max_triangles)
        if scene is not None:
            return scene
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


class _Tally:
    """A file that keeps only the count of the bytes written to it."""

    size = 0

    def write(self, data) -> int:
        size = memoryview(data).nbytes
        self.size += size
        return size


def pickled_size(value) -> int:
    """Bytes of ``value`` pickled (protocol 5), counted as they are written: the large
    arrays are handed over as buffers, never copied."""
    tally = _Tally()
    pickle.Pickler(tally, protocol=5).dump(value)
    return tally.size


def _parse_in_worker(path: str, file_type: str, root: str | None, max_triangles: int,
                     limits: LoadLimits | None, scenes: bool = False,
                     result_bytes: int | None = None,
                     set_limits: FileSetLimits | None = None):
    """``check_mesh_file`` in a parse worker, with every failure made a picklable
    MeshError naming ``path`` (the caller replaces it with the upload's name).

    A result that would pickle to more than ``result_bytes`` is refused here
    (OutOfMemory): sending it back needs it pickled whole in this worker, and
    unpickled whole in the server."""
    try:
        result = check_mesh_file(path, file_type=file_type, max_triangles=max_triangles,
                                 root=root, limits=limits, scenes=scenes,
                                 set_limits=set_limits)
        if result_bytes is not None:
            size = pickled_size(result)
            if size > result_bytes:
                raise OutOfMemory(f"cannot load {path}: what it holds once read takes {size} "
                                  f"bytes, more than the {result_bytes} this server hands over "
                                  "for one file")
        return result
    except MeshError:
        raise
    except MemoryError:
        raise OutOfMemory(f"cannot load {path}: reading it needs more memory than this server "
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
    result_bytes : int, optional
        Most bytes a parsed file may take pickled to be sent back (default half of
        ``memory_bytes``: the worker holds it and its pickle at once); past it the
        file is refused (:class:`OutOfMemory`).

    The processes start on the first parse (a server that never parses never
    pays for them) with the spawn method: a worker forked from a threaded
    server could inherit a lock held by another thread.
    """

    def __init__(self, *, workers: int = 1, queue: int = 4,
                 memory_bytes: int = PARSE_MEMORY_BYTES, result_bytes: int | None = None):
        self.workers, self.queue, self.memory_bytes = max(1, workers), max(0, queue), memory_bytes
        self.result_bytes = memory_bytes // 2 if result_bytes is None else result_bytes
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
              limits: LoadLimits | None, admit: bool = True, scenes: bool = False,
              set_limits: FileSetLimits | None = None):
        """``check_mesh_file`` in a worker; see :func:`_parse_in_worker`.

        Raises ParserBusy (``admit`` and the queue is full), ParserClosed,
        LimitError (too large, or the worker ran out of memory or died) and
        MeshError (not a usable mesh).
        """
        try:
            return self.call(_parse_in_worker, str(path), file_type,
                             None if root is None else str(root), max_triangles, limits,
                             scenes, self.result_bytes, set_limits, admit=admit)
        except _WorkerDied:
            raise LimitError(f"cannot load {Path(path).name}: reading it needed more memory "
                             "than this server allows one file, or crashed the reader") from None

    def call(self, function, *args, admit: bool = True):
        """Run the picklable ``function(*args)`` in a worker, waiting for a free one.

        Whatever goes wrong that is not the function's own MeshError (the worker
        dies, its result cannot be pickled or sent back, a MemoryError doing so)
        raises a LimitError subclass, and the pool is started afresh."""
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
                except OutOfMemory:
                    # the worker survived its address-space limit, but the heap it
                    # grew may stay mapped and fail the next file: a fresh pool
                    self._retire(executor, cancel=False)   # others' parses finish there
                    raise
                except BrokenProcessPool:
                    closed = self._retire(executor, cancel=True)
                    if closed:
                        raise ParserClosed("the server is shutting down; try again "
                                           "shortly") from None
                    raise _WorkerDied("the parse worker ran out of memory or crashed") from None
                except (MeshError, ParserBusy):
                    raise
                except MemoryError:
                    # sending a large result back (pickled whole in the worker):
                    # its heap may stay grown, a fresh pool
                    self._retire(executor, cancel=False)
                    raise _WorkerDied("the parse worker ran out of memory sending its "
                                      "result back") from None
                except Exception:       # noqa: BLE001
                    # not the job's own answer (the job makes every failure a MeshError)
                    # but the hand-over's: its result could not be pickled or sent back
                    self._retire(executor, cancel=False)
                    traceback.print_exc()
                    raise _WorkerDied("the parse worker could not send its result "
                                      "back") from None
        finally:
            with self._lock:
                self._admitted -= 1

    def _retire(self, executor: ProcessPoolExecutor, *, cancel: bool) -> bool:
        """Stop ``executor`` so the next parse starts a fresh pool (``cancel``: its
        waiting parses too); whether the pool was closed meanwhile."""
        with self._lock:
            closed = self._closed
            if self._executor is executor:
                self._executor = None
        executor.shutdown(wait=False, cancel_futures=cancel)
        return closed

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
