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
path, rather than an open file, uses it. The folder itself (bound, leases,
eviction, whole files only) is ``service/lru_folder.py``'s, shared with the
server's body files.
"""

from __future__ import annotations

import hashlib
import re
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from pathlib import Path

from .lru_folder import LruFolder

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
        self._files = LruFolder(self.folder, self.max_bytes, names=_NAME,
                                what="cached artefact file")
        self._lock = threading.Lock()
        self._pending: dict[str, Future] = {}
        self.hits = self.misses = 0

    @property
    def size(self) -> int:
        """Bytes of cached files now."""
        return self._files.size

    def __contains__(self, key: str) -> bool:
        return file_name(key) in self._files

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
                if self._files.touch(name):
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
                self._files.fetch(name, fetch)
            except BaseException as exc:
                with self._lock:
                    del self._pending[name]
                future.set_exception(exc)
                # nobody else may be waiting: mark the exception as retrieved
                future.exception()
                raise
            with self._lock:
                del self._pending[name]
            future.set_result(None)
            return self.folder / name

    @contextmanager
    def lease(self, key: str, fetch: Callable[[Path], None]) -> Iterator[Path]:
        """:meth:`path` with the file held in place until the ``with`` block ends."""
        name = file_name(key)
        while True:
            path = self.path(key, fetch)
            if self._files.lease(name) is not None:     # not evicted since path()
                break
        try:
            yield path
        finally:
            self._files.release(name)

    def open(self, key: str, fetch: Callable[[Path], None]):
        """``key``'s cached file opened for binary reading (readable to its end
        whatever is evicted meanwhile); the caller closes it."""
        with self.lease(key, fetch) as path:
            return open(path, "rb")

    def discard(self, key: str) -> None:
        """Forget ``key``'s file (a copy found damaged, say): the next use fetches it
        again. Readers that have it open keep reading it; a leased file is removed
        when its last lease ends."""
        self._files.discard(file_name(key))
