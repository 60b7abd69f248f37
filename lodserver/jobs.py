"""Background builds: a thread pool turning queued uploads into artefacts.

Each build loads the stored source, checks the limits, runs ``build.build``
(the numba kernel releases the GIL, so a worker thread does not stall the
server) and hands the result to the store. Progress goes to the store a few
times a second. A build that fails marks only its own mesh failed, with the
reason; a build cancelled by shutdown goes back to the queue for the next
process (``Store.recover``), and one cancelled by a delete is dropped.
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from .build import build
from .io import LoadReport, load_mesh
from .mesh import Mesh, MeshError
from .store import MeshRecord, Store, StoreError, UnknownMeshError

log = logging.getLogger(__name__)

DEFAULT_MAX_TRIANGLES = 2_000_000
# Seconds between progress writes: enough for a progress bar, few SQLite writes.
PROGRESS_INTERVAL = 0.5


class LimitError(MeshError):
    """An upload exceeds a configured limit (bytes or triangles)."""


def check_mesh_file(path, *, file_type: str, max_triangles: int) -> tuple[Mesh, LoadReport]:
    """Load a mesh file and check it against the triangle limit.

    Parameters
    ----------
    path : path of the file; file_type : one of ``io.SUPPORTED_INPUT``.
    max_triangles : int
        Most triangles accepted after cleaning.

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
    mesh, report = load_mesh(path, file_type=file_type)
    if mesh.face_count > max_triangles:
        raise LimitError(f"the mesh has {mesh.face_count} triangles; this server builds at most "
                         f"{max_triangles}")
    return mesh, report


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
    """

    def __init__(self, store: Store, *, workers: int = 1,
                 max_triangles: int = DEFAULT_MAX_TRIANGLES):
        self.store = store
        self.max_triangles = max_triangles
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
            self._pool.submit(warm_up)
        for mesh_id in self.store.recover():
            self.submit(mesh_id)

    def accept(self, *, source: Path, name: str, file_type: str, options: dict) -> MeshRecord:
        """Check an uploaded file and queue its build.

        The file is loaded once here so that a file that is not a usable mesh
        is refused at once (``MeshError``, ``LimitError``, naming ``name``)
        rather than failing later in the background. ``source`` is moved into
        the store, or deleted if refused.
        """
        try:
            try:
                parsed = check_mesh_file(source, file_type=file_type,
                                         max_triangles=self.max_triangles)
            except MeshError as exc:
                raise type(exc)(str(exc).replace(str(source), name)) from exc
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
        except Exception:
            # A bug, not bad input: log it and fail this mesh only.
            log.exception("build of mesh %s failed", mesh_id)
            settled = True
            try:
                self.store.mark_failed(mesh_id=mesh_id, reason="internal error while building; "
                                       "the server log has the details")
            except StoreError:
                pass
        finally:
            with self._lock:
                self._cancel.pop(mesh_id, None)
            if not settled and self._closing:
                try:
                    self.store.requeue(mesh_id=mesh_id)
                except StoreError:
                    pass

    def _build(self, mesh_id: str, cancel: threading.Event) -> bool:
        """Build one mesh; False if cancelled before it was ready or failed."""
        store = self.store
        record = store.get(mesh_id=mesh_id)
        source = store.source_path(mesh_id=mesh_id)
        store.mark_building(mesh_id=mesh_id)
        with self._lock:
            parsed = self._parsed.pop(mesh_id, None)
        try:
            mesh, report = parsed or check_mesh_file(source, file_type=record.file_type,
                                                     max_triangles=self.max_triangles)
        except MeshError as exc:
            # name the upload, not the server's file
            store.mark_failed(mesh_id=mesh_id, reason=str(exc).replace(str(source), record.name))
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
