"""A bounded, leased, least-recently-used folder of files.

Two caches keep files on the local disk: the artefacts a server read from a
shared store (``service/cache.py``) and the large response bodies it encoded
(``api/caching.py``). Both are a folder of immutable files named by their
content, bounded in bytes, whose least recently used files go first, and whose
files in use must stay where they are: that folder is :class:`LruFolder`.

A file is *leased* while a caller needs its path (a response streaming it, a
loader opening it): eviction skips it, and a file discarded while leased is
removed when its last lease ends. A file reaches its final name only whole
(written or fetched under a temporary name starting with ``.``, flushed to
disk, renamed), so a reader never sees part of one, even after a crash; the
temporary files a crash leaves are removed when the folder is opened.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import uuid
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

from ..io.files import write_atomic

log = logging.getLogger(__name__)


class LruFolder:
    """Files by name in one folder, at most ``capacity`` bytes, LRU first out.

    Parameters
    ----------
    folder : Path
        The folder, created if absent. Files a previous run left whose names
        match ``names`` are kept (their names say their content, so they are
        still right), least recently modified first in line for eviction; the
        temporary files of an interrupted write are removed; anything else is
        left alone.
    capacity : int
        Most bytes of files (and of writes under way) kept. Leased files are
        never evicted, so the bound can be exceeded by the files in use.
    names : re.Pattern
        The names of the folder's own files.
    what : str
        What a file is, for the log (``"body file"``).

    The folder is this process's: its byte bound is kept by this object's
    accounting, all of it under one lock.
    """

    def __init__(self, folder, capacity: int, *, names: re.Pattern, what: str):
        self.folder = Path(folder)
        self.capacity = capacity
        self.what = what
        self._lock = threading.Lock()
        self._sizes: OrderedDict[str, int] = OrderedDict()    # name -> bytes, LRU first
        self._leases: dict[str, int] = {}
        self._doomed: set[str] = set()      # discarded while leased: removed on release
        self._reserved = 0                  # bytes of writes under way
        self.folder.mkdir(parents=True, exist_ok=True)
        found = []
        for entry in os.scandir(self.folder):
            if entry.name.startswith("."):
                self._remove(entry.path)
            elif names.fullmatch(entry.name) and entry.is_file(follow_symlinks=False):
                stat = entry.stat(follow_symlinks=False)
                found.append((stat.st_mtime_ns, entry.name, stat.st_size))
        for _, name, size in sorted(found):       # oldest first: the first to go
            self._sizes[name] = size
        with self._lock:
            self._make_room(0)

    @property
    def size(self) -> int:
        """Bytes held now (files and writes under way)."""
        with self._lock:
            return sum(self._sizes.values()) + self._reserved

    def __contains__(self, name: str) -> bool:
        with self._lock:
            return name in self._sizes

    def touch(self, name: str) -> bool:
        """Whether ``name``'s file is here, made the most recently used if it is."""
        with self._lock:
            if name not in self._sizes:
                return False
            self._sizes.move_to_end(name)
            return True

    def lease(self, name: str) -> tuple[Path, int] | None:
        """(path, bytes) of ``name``'s file, made the most recently used and held in
        place until :meth:`release`; None if absent."""
        with self._lock:
            size = self._sizes.get(name)
            if size is None:
                return None
            self._sizes.move_to_end(name)
            self._leases[name] = self._leases.get(name, 0) + 1
        return self.folder / name, size

    def release(self, name: str) -> None:
        """End one lease of ``name``; after the last, a discarded file is removed and
        the bound kept again."""
        with self._lock:
            left = self._leases.pop(name, 0) - 1
            if left > 0:
                self._leases[name] = left
            elif name in self._doomed:
                self._doomed.discard(name)
                self._remove(self.folder / name)
            else:
                self._make_room(0)

    def discard(self, name: str) -> None:
        """Forget ``name``'s file: removed now, or when its last lease ends (readers
        that have it open keep reading it)."""
        with self._lock:
            if self._sizes.pop(name, None) is None:
                return
            if name in self._leases:
                self._doomed.add(name)
            else:
                self._remove(self.folder / name)

    def write(self, name: str, body) -> bool:
        """Write ``body`` (bytes-like) as ``name``'s file, room made first.

        Returns
        -------
        bool
            True when the file is here (written now or before), False (nothing
            written) when unleased files cannot make room for it.

        Raises
        ------
        OSError
            If the write fails (the disk is full, say); nothing is kept then.
        """
        size = body.nbytes if isinstance(body, memoryview) else len(body)
        with self._lock:
            if name in self._sizes:
                return True
            if not self._make_room(size):
                return False
            self._reserved += size
        written = False
        try:
            write_atomic(self.folder / name, body)     # never a partial file
            written = True
        finally:
            with self._lock:
                self._reserved -= size
                if written:
                    self._add(name, size)
        return True

    def fetch(self, name: str, fetch: Callable[[Path], None]) -> None:
        """Make ``name``'s file by ``fetch(dest)``, which writes the whole file to
        ``dest`` (a temporary path in the folder) or raises; its size is known only
        after, so room is made then, sparing this file (a file larger than the
        whole bound stays until the next one comes). Its error is raised here and
        nothing is kept."""
        temporary = self.folder / f".{name}.{uuid.uuid4().hex}.tmp"
        try:
            fetch(temporary)
            # fsynced: a crash must not leave a torn file under a final name
            with open(temporary, "rb+") as file:
                os.fsync(file.fileno())
            size = temporary.stat().st_size
            os.replace(temporary, self.folder / name)
        except BaseException:
            self._remove(temporary)
            raise
        with self._lock:
            self._add(name, size)

    def _add(self, name: str, size: int) -> None:
        """Count ``name``'s file, now under its name, and keep the bound sparing it
        (with the lock held)."""
        self._sizes.setdefault(name, size)
        self._doomed.discard(name)     # the file under the name is the new one
        self._make_room(0, keep=name)

    def _make_room(self, size: int, keep: str | None = None) -> bool:
        """Remove unleased files other than ``keep``, least recently used first,
        until ``size`` more bytes fit (with the lock held); False if they cannot."""
        held = sum(self._sizes.values()) + self._reserved
        if held + size <= self.capacity:
            return True
        for name in list(self._sizes):
            if name == keep or name in self._leases:
                continue
            held -= self._sizes.pop(name)
            self._remove(self.folder / name)
            if held + size <= self.capacity:
                return True
        return False

    def _remove(self, path) -> None:
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("could not remove a %s: %s", self.what, exc)
