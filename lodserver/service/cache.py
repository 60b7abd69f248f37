"""A server's bounded local cache of artefacts read from a shared store.

When the store is an object store (``s3://...``), every server keeps the
artefacts it has read in a folder of its own, so a hot mesh is fetched from the
store once, not per request, and is still there after a restart. Keys are
content-addressed (``artefacts/<sha256>.pm``): the bytes under a key never
change, so a cached file is never stale and needs no revalidation.

:class:`ArtefactCache` holds at most ``max_bytes`` (``LODSERVER_CACHE_BYTES``)
of files, dropping the least recently used first. A miss is fetched by the
caller's ``fetch(dest_path)`` into a temporary file, flushed to disk and
renamed, so a file under its final name is always whole, even after a crash;
concurrent misses of one key in this process fetch it once and share the
result (or the error). One folder belongs to one process: the byte bound is
kept by that process's accounting.

A file being read is never cut short by eviction: on POSIX an unlinked file
stays readable through descriptors already open, and :meth:`ArtefactCache.lease`
holds a file in place (no eviction, no unlink) while a caller that needs its
path, rather than an open file, uses it.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import threading
import uuid
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger(__name__)

# The default bound when LODSERVER_CACHE_BYTES is not set: room for a few of the
# largest artefacts (a million-face mesh's .pm is about 140 MB).
DEFAULT_CACHE_BYTES = 2 * 2**30

# A cached file is named by the SHA-256 of its key (any key maps to a safe flat
# name); temporary files start with "." and are removed when a cache opens.
_NAME = re.compile(r"[0-9a-f]{64}")


def file_name(key: str) -> str:
    """The cache's file name of ``key``: its SHA-256 in hex."""
    return hashlib.sha256(key.encode()).hexdigest()


class ArtefactCache:
    """Local copies of immutable objects, by key, bounded in bytes, LRU.

    Parameters
    ----------
    folder : Path
        The cache's folder, created if absent. Files a previous run left are kept
        (their keys are content-addressed, so still right), least recently
        modified first in line for eviction; temporary files are removed.
    max_bytes : int
        Most bytes of cached files kept. A file is evicted only when it is not
        leased and not the one just fetched, so the bound can be exceeded by the
        files in use at that moment (a single file larger than the whole cache is
        still served, then dropped at the next fetch).
    """

    def __init__(self, folder, max_bytes: int = DEFAULT_CACHE_BYTES):
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be at least 0, got {max_bytes}")
        self.folder = Path(folder).absolute()
        self.max_bytes = int(max_bytes)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._sizes: OrderedDict[str, int] = OrderedDict()     # name -> bytes, LRU first
        self._leases: dict[str, int] = {}
        self._pending: dict[str, Future] = {}
        self._doomed: set[str] = set()      # discarded while leased: removed on release
        self.hits = self.misses = 0
        found = []
        for entry in os.scandir(self.folder):
            if entry.name.startswith("."):
                _remove(entry.path)
            elif _NAME.fullmatch(entry.name) and entry.is_file(follow_symlinks=False):
                stat = entry.stat(follow_symlinks=False)
                found.append((stat.st_mtime_ns, entry.name, stat.st_size))
        for _, name, size in sorted(found):
            self._sizes[name] = size
        with self._lock:
            self._evict(keep=None)

    @property
    def size(self) -> int:
        """Bytes of cached files now."""
        with self._lock:
            return sum(self._sizes.values())

    def __contains__(self, key: str) -> bool:
        with self._lock:
            return file_name(key) in self._sizes

    def path(self, key: str, fetch: Callable[[Path], None]) -> Path:
        """The local file holding ``key``'s bytes, fetched on a miss.

        ``fetch(dest)`` must write the whole object to the file ``dest`` (a
        temporary path in the cache folder) or raise; its error is raised here, to
        every caller waiting on the same miss, and nothing is cached. The path is
        the most recently used file, so only later fetches can evict it: a caller
        that must be sure it stays should use :meth:`lease` or :meth:`open`.
        """
        name = file_name(key)
        while True:
            with self._lock:
                if name in self._sizes:
                    self._sizes.move_to_end(name)
                    self.hits += 1
                    return self.folder / name
                future = self._pending.get(name)
                owner = future is None
                if owner:
                    future = self._pending[name] = Future()
                    self.misses += 1
            if not owner:
                # another thread is fetching this key: wait for it, then look again
                # (its file may, rarely, be evicted already: then fetch it anew)
                future.result()
                continue
            try:
                size = self._fetch(name, fetch)
            except BaseException as exc:
                with self._lock:
                    del self._pending[name]
                future.set_exception(exc)
                # nobody else may be waiting: mark the exception as retrieved
                future.exception()
                raise
            with self._lock:
                self._sizes[name] = size
                self._doomed.discard(name)     # the file under the name is the new one
                del self._pending[name]
                self._evict(keep=name)
            future.set_result(None)
            return self.folder / name

    @contextmanager
    def lease(self, key: str, fetch: Callable[[Path], None]) -> Iterator[Path]:
        """:meth:`path` with the file held in place until the ``with`` block ends."""
        name = file_name(key)
        while True:
            path = self.path(key, fetch)
            with self._lock:
                if name in self._sizes:      # not evicted between path() and here
                    self._leases[name] = self._leases.get(name, 0) + 1
                    break
        try:
            yield path
        finally:
            with self._lock:
                left = self._leases.pop(name) - 1
                if left:
                    self._leases[name] = left
                elif name in self._doomed:
                    self._doomed.discard(name)
                    _remove(self.folder / name)
                else:
                    self._evict(keep=None)

    def open(self, key: str, fetch: Callable[[Path], None]):
        """``key``'s cached file opened for binary reading (readable to its end
        whatever is evicted meanwhile); the caller closes it."""
        with self.lease(key, fetch) as path:
            return open(path, "rb")

    def discard(self, key: str) -> None:
        """Forget ``key``'s file (a copy found damaged, say): the next use fetches it
        again. Readers that have it open keep reading it; a leased file is removed
        when its last lease ends."""
        name = file_name(key)
        with self._lock:
            if self._sizes.pop(name, None) is None:
                return
            if name in self._leases:
                self._doomed.add(name)
            else:
                _remove(self.folder / name)

    def _fetch(self, name: str, fetch: Callable[[Path], None]) -> int:
        """Fetch into a temporary file, flush it to disk, rename it; its size."""
        temporary = self.folder / f".{name}.{uuid.uuid4().hex}.tmp"
        try:
            fetch(temporary)
            # fsynced: a crash must not leave a torn file under a final name, which
            # a later load would take for a corrupt artefact in the shared store
            with open(temporary, "rb+") as file:
                os.fsync(file.fileno())
            size = temporary.stat().st_size
            os.replace(temporary, self.folder / name)
        except BaseException:
            _remove(temporary)
            raise
        return size

    def _evict(self, *, keep: str | None) -> None:
        """Remove least recently used files until the cache fits ``max_bytes``,
        sparing leased files and ``keep`` (with the lock held)."""
        held = sum(self._sizes.values())
        if held <= self.max_bytes:
            return
        for name in list(self._sizes):
            if name == keep or name in self._leases:
                continue
            held -= self._sizes.pop(name)
            _remove(self.folder / name)
            if held <= self.max_bytes:
                return


def _remove(path) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    except OSError as exc:
        log.warning("could not remove a cached artefact file: %s", exc)
