"""Background builds: a thread pool turning queued uploads into artefacts.

Each build takes the mesh parsed when its upload was checked (``parsing``), or
(a build resumed after a restart) parses the stored source again through the
same pool, runs ``build.build`` (the numba kernel releases the GIL, so a worker
thread does not stall the server) and hands the result to the store. Progress
goes to the store a few times a second. A build that fails marks only its own
mesh failed, with the reason (running out of disk space says so); a build
cancelled by shutdown goes back to the queue for the next process
(``Store.recover``), and one cancelled by a delete is dropped.
"""

from __future__ import annotations

import logging
import os
import shutil
import sqlite3
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..build import build
from ..io import LoadReport
from ..io.limits import DEFAULT_MAX_TRIANGLES, LoadLimits
from ..mesh import Mesh, MeshError
from .parsing import ParsePool, ParserClosed, check_mesh_file
from .store import MeshRecord, Store, StorageFullError, StoreError, UnknownMeshError, is_disk_full

__all__ = ["JobRunner", "warm_up"]

log = logging.getLogger(__name__)

# Seconds between progress writes: enough for a progress bar, few SQLite writes.
PROGRESS_INTERVAL = 0.5
_DISK_FULL = ("the server ran out of disk space while building; upload the mesh again once "
              "space is freed")

def warm_up() -> None:
    """Build a tiny mesh and encode its packets both ways, so numba loads (or
    compiles) every kernel before a real build or the first packet request."""
    from ..packets import encode_packet, packet_between

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
    from ..packets import encode_records

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
            from ..simplify.topology import census
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
