"""Background builds: threads claiming queued uploads and turning them into artefacts.

The build queue is the catalogue (``catalog.py``), shared by every server and
``lodserver worker`` with the same ``LODSERVER_CATALOG_URL``. Each of a runner's
``workers`` threads claims a build (the uploads submitted here first, then,
once :meth:`JobRunner.start` ran, any queued build or one whose lease ran
out), holds it under a lease that a heartbeat thread renews every third of
its length, and writes its progress and result fenced by the claim: a build
whose lease was taken over (its process stalled or was cut off) or whose mesh
was deleted, on this server or another, sees its next write refused and stops,
and never records a second completion.

A build takes the mesh parsed when its upload was checked (``parsing``) when
this process accepted the upload, or parses the stored source again through
the same pool, runs ``build.build`` (the numba kernel releases the GIL, so a
worker thread does not stall the server) and hands the result to the store.
Progress goes to the store a few times a second. A build that fails marks
only its own mesh failed, with the reason (running out of disk space says
so); a build cancelled by shutdown goes back to the queue for any process,
and one cancelled by a delete is dropped.
"""

from __future__ import annotations

import logging
import os
import shutil
import sqlite3
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from pathlib import Path

from ..build import build
from ..io import LoadReport
from ..io.fileset import FileSetLimits
from ..io.limits import DEFAULT_MAX_TRIANGLES, LoadLimits
from ..io.scene import Scene
from ..mesh import Mesh, MeshError
from ..scene.build import build_asset
from ..scene.load import SceneReport
from .catalog import CatalogUnavailable
from .errors import StoreUnavailable
from .parsing import ParsePool, ParserClosed, check_mesh_file
from .store import (Claim, LeaseLostError, MeshRecord, Store, StorageFullError, StoreError,
                    UnknownMeshError, is_disk_full)
from .warm import warm_up

__all__ = ["JobRunner", "LEASE_SECONDS", "POLL_SECONDS"]

log = logging.getLogger(__name__)

# Seconds between progress writes: enough for a progress bar, few catalogue writes.
PROGRESS_INTERVAL = 0.5
# A build's lease, in seconds: how long a build whose process died waits before
# another process takes it over. Renewed every third of it, so a renewal may
# be late twice (a loaded machine, a slow catalogue) before the lease is lost.
LEASE_SECONDS = 15.0
# Seconds between looks at the queue by an idle runner that builds for everyone.
POLL_SECONDS = 1.0
# Seconds an idle runner waits before its next claim after a build stopped on an
# unreachable catalogue or store, rather than claim, fail and requeue in a loop.
OUTAGE_PAUSE = 2.0
_DISK_FULL = ("the server ran out of disk space while building; upload the mesh again once "
              "space is freed")


def _prepare_packets(store: Store, mesh_id: str) -> None:
    """Encode every record of a ready mesh both ways, so that its first packet
    request is a slice, not a walk over every split (seconds on a million faces)."""
    from ..packets import encode_records

    try:
        for part in store.load(mesh_id=mesh_id).parts:
            encode_records(part.pm)
    except Exception:       # the mesh is served either way; its first packet is just slower
        log.exception("could not prepare the packets of mesh %s", mesh_id)



@dataclass
class _Build:
    """A build this runner holds: its claim, its stop signal, its last renewal."""

    claim: Claim
    cancel: threading.Event = field(default_factory=threading.Event)
    renewed: float = field(default_factory=time.monotonic)
    lost: bool = False
    _losing: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def lose(self) -> None:
        """Stop this build: its lease is gone (the mesh deleted, or taken over).

        Said once, by whichever thread learns it first: the heartbeat, or the
        progress callback whose fenced write was refused. A build stopped without
        a word is indistinguishable, in the log, from one that stalled.
        """
        with self._losing:
            first, self.lost = not self.lost, True
        if first:
            log.warning("the build of mesh %s lost its lease (deleted, or taken over); "
                        "stopping it", self.claim.mesh_id)
        self.cancel.set()


class JobRunner:
    """Builds from a store's queue in worker threads, under leases.

    Parameters
    ----------
    store : Store
    workers : int
        Concurrent builds; each takes one core while its kernel runs. 0 builds
        nothing here (the uploads accepted wait for another server or a
        ``lodserver worker``).
    max_triangles : int
        Triangle limit checked again at build time (settings may have changed).
    parser : ParsePool, optional
        Where files are parsed (the server's); None parses in the calling
        thread, unbounded (a trusted caller's own files).
    lease_seconds : float
        The lease of a claimed build (:data:`LEASE_SECONDS`).
    poll_seconds : float
        How often idle workers look for builds queued by other processes.
    set_limits : FileSetLimits, optional
        What a stored set (a zip) may unpack to when it is parsed.

    Until :meth:`start`, only the builds :meth:`submit`-ted here are claimed.
    ``ready`` is set once the kernels are warm (``start(warm=True)``) or at
    once without warming: until then a build would sit compiling.
    """

    def __init__(self, store: Store, *, workers: int = 1,
                 max_triangles: int = DEFAULT_MAX_TRIANGLES, parser: ParsePool | None = None,
                 lease_seconds: float = LEASE_SECONDS, poll_seconds: float = POLL_SECONDS,
                 set_limits: FileSetLimits | None = None):
        if lease_seconds <= 0 or poll_seconds <= 0:
            raise ValueError("lease_seconds and poll_seconds must be positive")
        self.store = store
        self.workers = max(0, int(workers))
        self.max_triangles = max_triangles
        self.parser = parser
        self.lease_seconds = float(lease_seconds)
        self.poll_seconds = float(poll_seconds)
        self.set_limits = set_limits
        self.ready = threading.Event()
        self.warmed_at: float | None = None
        # Meshes parsed when their upload was checked, for their build to reuse:
        # a million-face file is not parsed twice. Only a few are kept (memory),
        # the oldest dropped (another process may have built it); the others,
        # and builds of uploads to other processes, parse their file again.
        self._parsed: OrderedDict[str, tuple] = OrderedDict()   # id -> what parse returned
        self._keep_parsed = max(1, self.workers) + 1
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._wanted: deque[str] = deque()      # submitted here: claimed first
        self._claim_any = False                 # also builds queued by others (start)
        self._idle_until = 0.0                  # the queue was empty: next look then
        self._active: dict[str, _Build] = {}
        self._threads: list[threading.Thread] = []
        self._stopped = threading.Event()       # the heartbeat's end
        self._closing = False

    # ---- starting and stopping ----------------------------------------------------
    def start(self, *, warm: bool = True) -> None:
        """Warm the kernels, settle the builds this node's previous process left,
        then build from the whole queue."""
        if warm:
            threading.Thread(target=self._warm, name="warm-kernels", daemon=True).start()
        else:
            self.ready.set()
        pending = self.store.recover()
        with self._wake:
            self._claim_any = True
            self._wanted.extend(pending)
            self._wake.notify_all()
        self._start_threads()

    def _start_threads(self) -> None:
        with self._lock:
            if self._threads or self._closing or self.workers == 0:
                return
            self._threads = [threading.Thread(target=self._work, name=f"build-{n}", daemon=True)
                             for n in range(self.workers)]
            self._threads.append(threading.Thread(target=self._heartbeat, name="build-leases",
                                                  daemon=True))
        for thread in self._threads:
            thread.start()

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

    def shutdown(self) -> None:
        """Cancel every build and wait for the workers; unfinished builds go back to
        the queue (for any process, at once: their leases are given up)."""
        with self._wake:
            self._closing = True
            builds = list(self._active.values())
            self._wake.notify_all()
        for running in builds:
            running.cancel.set()
        if self.parser is not None:
            self.parser.shutdown()      # a build waiting on a parse stops waiting
        self._stopped.set()
        for thread in self._threads:
            thread.join()

    # ---- uploads ----------------------------------------------------------------
    def parse(self, source: Path, *, file_type: str, name: str, root=None,
              admit: bool = True) -> tuple[Mesh | Scene, LoadReport | SceneReport]:
        """Parse and check ``source`` (in the parse pool when there is one): a
        glTF scene (``scene.load.scene_reason``) as ``(Scene, SceneReport)``.

        Messages name ``name``, never ``source``, ``root`` or the data directory.
        """
        limits = LoadLimits(max_triangles=self.max_triangles)
        try:
            if self.parser is None:
                return check_mesh_file(source, file_type=file_type, root=root,
                                       max_triangles=self.max_triangles, limits=limits,
                                       set_limits=self.set_limits, scenes=True)
            return self.parser.parse(source, file_type=file_type, root=root, limits=limits,
                                     max_triangles=self.max_triangles, admit=admit, scenes=True,
                                     set_limits=self.set_limits)
        except MeshError as exc:
            message = scrub(str(exc), {source: name, root: "the upload",
                                       getattr(self.store, "root", None): "the server"})
            # the loader names the file by its base name: a stored source's is its id
            exc.args = (message.replace(Path(source).name, name),)
            raise

    def accept(self, *, source: Path, name: str, file_type: str, options: dict,
               root: Path | None = None, with_report: bool = False):
        """Check an uploaded file and queue its build; its MeshRecord (and, with
        ``with_report``, the parse's LoadReport after it, as a pair).

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
        if self.workers:
            with self._lock:
                self._parsed[record.id] = parsed
                while len(self._parsed) > self._keep_parsed:
                    self._parsed.popitem(last=False)
        self.submit(record.id)
        return (record, parsed[1]) if with_report else record

    def forget(self, *, mesh_id: str) -> None:
        """Delete a mesh, stopping its build if it runs here (a build elsewhere
        stops at its next write, which the deleted row refuses)."""
        self.store.get(mesh_id=mesh_id)
        self.cancel(mesh_id)
        self.store.delete(mesh_id=mesh_id)

    def submit(self, mesh_id: str) -> None:
        """Build ``mesh_id`` here next, if it is still queued when a worker is free."""
        if self.workers == 0:
            return
        with self._wake:
            if self._closing:
                return
            self._wanted.append(mesh_id)
            self._wake.notify()
        self._start_threads()

    def cancel(self, mesh_id: str) -> None:
        """Stop a queued or running build (its mesh is being deleted)."""
        with self._lock:
            self._parsed.pop(mesh_id, None)
            running = self._active.get(mesh_id)
        if running is not None:
            running.cancel.set()

    # ---- the workers --------------------------------------------------------------
    def _next(self) -> tuple[bool, str | None]:
        """Wait for something to claim: (False, None) to stop, (True, id) for a
        submitted mesh, (True, None) for whatever the queue holds."""
        with self._wake:
            while True:
                if self._closing:
                    return False, None
                if self._wanted:
                    return True, self._wanted.popleft()
                wait = None
                if self._claim_any:
                    wait = self._idle_until - time.monotonic()
                    if wait <= 0:
                        return True, None
                self._wake.wait(wait)

    def _work(self) -> None:
        while True:
            go, mesh_id = self._next()
            if not go:
                return
            try:
                claim = self.store.claim(lease_seconds=self.lease_seconds, mesh_id=mesh_id)
            except Exception as exc:
                # the catalogue is unreachable (say): look again after a pause (the
                # mesh stays queued, for whoever looks next)
                log.warning("could not claim a build: %s", exc)
                claim, mesh_id = None, None
            if claim is None:
                if mesh_id is None:     # nothing queued: the next look after a pause
                    with self._lock:
                        self._idle_until = time.monotonic() + self.poll_seconds
                continue
            self._run(claim)

    def _heartbeat(self) -> None:
        """Renew the leases of the builds held here; stop those whose lease is lost."""
        while not self._stopped.wait(self.lease_seconds / 3):
            with self._lock:
                builds = list(self._active.values())
            for running in builds:
                try:
                    held = self.store.renew(claim=running.claim, lease_seconds=self.lease_seconds)
                except Exception as exc:
                    # cannot tell: give up only once the lease has surely run out
                    log.warning("could not renew the lease of mesh %s: %s",
                                running.claim.mesh_id, exc)
                    held = time.monotonic() - running.renewed < self.lease_seconds
                else:
                    if held:
                        running.renewed = time.monotonic()
                if not held:
                    running.lose()

    def _run(self, claim: Claim) -> None:
        mesh_id = claim.mesh_id
        running = _Build(claim)
        with self._lock:
            self._active[mesh_id] = running
            if self._closing:
                running.cancel.set()
        settled = False   # ready or failed, or no longer ours: nothing to give back
        try:
            if not running.cancel.is_set():
                settled = self._build(running)
        except UnknownMeshError:
            settled = True  # deleted meanwhile
        except LeaseLostError as exc:
            # another process builds it now. Said here too, not only by the
            # heartbeat: a compiled kernel holding the interpreter can keep the
            # heartbeat from running until the build's fenced write is refused.
            if not running.lost:
                log.warning("%s; its result is dropped", exc)
            settled = True
        except ParserClosed:
            pass            # shutting down: requeued below
        except (CatalogUnavailable, StoreUnavailable) as exc:
            # not the mesh's fault: it is given back below if the catalogue answers
            # again, else its lease runs out and any process builds it again. An
            # artefact stored whose answer was lost is stored again under the same
            # key (builds are deterministic). The idle workers pause first: a
            # claim now would meet the same outage.
            log.warning("the build of mesh %s stopped: %s", mesh_id, exc)
            with self._lock:
                self._idle_until = time.monotonic() + max(self.poll_seconds, OUTAGE_PAUSE)
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
                self.store.mark_failed(mesh_id=mesh_id, reason=reason, attempt=claim.attempt)
            except (StoreError, OSError, sqlite3.Error):
                log.exception("could not record the failure of mesh %s", mesh_id)
        finally:
            with self._lock:
                self._active.pop(mesh_id, None)
            if not settled and not running.lost:
                try:
                    self.store.requeue(mesh_id=mesh_id, attempt=claim.attempt)
                except (StoreError, OSError, sqlite3.Error):
                    pass    # deleted, taken over, or unreachable: the lease runs out

    def _parse_stored(self, record: MeshRecord) -> tuple[Mesh | Scene, LoadReport | SceneReport]:
        """Parse a stored source again (a build of an upload to another process, or
        resumed after a restart), by the upload's rule: alone in a folder of its own."""
        folder = self.store.scratch(prefix="build-")
        try:
            staged = self.store.stage_source(mesh_id=record.id, folder=folder)
            return self.parse(staged, file_type=record.file_type, name=record.name,
                              root=folder, admit=False)
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def _build(self, running: _Build) -> bool:
        """Build one claimed mesh; False if cancelled before it was ready or failed."""
        store, record, cancel = self.store, running.claim.record, running.cancel
        mesh_id, attempt = record.id, running.claim.attempt
        with self._lock:
            parsed = self._parsed.pop(mesh_id, None)
        try:
            source, report = parsed or self._parse_stored(record)
        except (MeshError, StoreError) as exc:
            if isinstance(exc, (UnknownMeshError, LeaseLostError, StoreUnavailable)):
                raise
            store.mark_failed(mesh_id=mesh_id, reason=str(exc), attempt=attempt)
            return True

        last = [0.0]

        def progress(done, expected):
            now = time.monotonic()
            if now - last[0] < PROGRESS_INTERVAL:
                return
            last[0] = now
            try:
                store.set_progress(mesh_id=mesh_id, progress=min(done / max(expected, 1), 0.99),
                                   attempt=attempt)
            except (UnknownMeshError, LeaseLostError):
                running.lose()          # deleted, or taken over: stop at once
            except Exception as exc:     # a progress bar is not worth a build
                log.warning("could not record the progress of mesh %s: %s", mesh_id, exc)

        options = dict(record.options)
        lock_border = bool(options.pop("lock_border", False))
        try:
            # every part built before anything is stored: a part that fails, or a
            # cancel, leaves nothing
            asset = build_asset(source, build=build, options=options, lock_border=lock_border,
                                progress=progress, cancel=cancel)
        except MeshError as exc:
            store.mark_failed(mesh_id=mesh_id, reason=str(exc), attempt=attempt)
            return True
        if asset is None or cancel.is_set():
            return False  # a cut-short decimation is not the mesh's progressive mesh
        # a single mesh's metadata is its progressive mesh's, which has its options
        asset.metadata.update(source=record.name, load_report=report.as_dict(),
                              options=asset.parts[0].pm.metadata.get("options",
                                                                     dict(record.options)))
        store.put_artefact(mesh_id=mesh_id, asset=asset, attempt=attempt,
                           patience=self.lease_seconds)
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
