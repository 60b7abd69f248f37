"""Immutable responses: ETags, 304s, and the two caches of encoded bodies.

An artefact never changes once written and ids are never reused, so a level or
a packet is fully named by the artefact's digest and the request's resolved
parameters: that name is the ETag, and the response may be cached for a year.

Small bodies are kept in memory (:class:`BodyCache`). Large ones (a LOD chain,
a full-detail json level: tens to hundreds of megabytes) are written once to an
immutable file named by their ETag (:class:`BodyFiles`) and streamed from it in
64 KiB reads (:class:`BodyFileResponse`), so serving one costs no memory and
the next request for it no encoding, even after a restart.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import threading
from collections import OrderedDict
from pathlib import Path

from fastapi import Request, Response
from starlette.responses import FileResponse

from ..io.files import write_atomic
from ..packets import PACKET_VERSION

log = logging.getLogger(__name__)

IMMUTABLE = "public, max-age=31536000, immutable"
# Encoded bodies kept in memory, by total size: repeated requests skip the encoder.
CACHE_BYTES = 128 * 2**20


def etag_for(digest: str, *parts) -> str:
    """A strong ETag for the response named by an artefact digest and parameters."""
    name = ":".join(str(part) for part in (digest, PACKET_VERSION, *parts))
    return '"' + hashlib.sha256(name.encode()).hexdigest()[:32] + '"'


def is_fresh(request: Request, etag: str) -> bool:
    """Whether the client's If-None-Match already names ``etag``."""
    header = request.headers.get("if-none-match")
    if not header:
        return False
    tags = {tag.strip().removeprefix("W/") for tag in header.split(",")}
    return "*" in tags or etag in tags


class BufferResponse(Response):
    """A response whose body is any bytes-like object (bytes or a byte memoryview),
    sent as it is: a level of tens of megabytes is not copied once more."""

    def render(self, content) -> bytes | memoryview:
        return b"" if content is None else content


def immutable_headers(etag: str, filename: str | None = None) -> dict:
    """ETag and a one-year Cache-Control, and the file name to save under, if any."""
    headers = {"ETag": etag, "Cache-Control": IMMUTABLE}
    if filename:
        headers["Content-Disposition"] = f'inline; filename="{filename}"'
    return headers


def immutable(body: bytes | memoryview | None, *, media_type: str, etag: str,
              filename: str | None = None) -> Response:
    """The response for ``body``, or a 304 when ``body`` is None."""
    if body is None:
        return Response(status_code=304, headers=immutable_headers(etag))
    return BufferResponse(body, media_type=media_type, headers=immutable_headers(etag, filename))


def body_size(body: bytes | memoryview) -> int:
    """Bytes in ``body`` (a memoryview's ``len`` counts items, not bytes)."""
    return body.nbytes if isinstance(body, memoryview) else len(body)


class BodyCache:
    """A thread-safe LRU of response bodies by ETag, bounded in bytes."""

    def __init__(self, capacity: int = CACHE_BYTES):
        self.capacity = capacity
        self._items: OrderedDict[str, bytes | memoryview] = OrderedDict()
        self._size = 0
        self._lock = threading.Lock()

    def get(self, key: str) -> bytes | memoryview | None:
        with self._lock:
            body = self._items.get(key)
            if body is not None:
                self._items.move_to_end(key)
            return body

    def put(self, key: str, body: bytes | memoryview) -> bool:
        """Keep ``body`` (dropping the least recently used); False if it is larger
        than the whole cache."""
        size = body_size(body)
        if size > self.capacity:
            return False
        with self._lock:
            if key not in self._items:
                self._items[key] = body
                self._size += size
            while self._size > self.capacity:
                _, dropped = self._items.popitem(last=False)
                self._size -= body_size(dropped)
        return True


# A body file is named by its ETag's hex digits; a name starting with "." is a
# temporary file of an interrupted write (write_atomic's); anything else is not ours.
_NAME = re.compile(r"[0-9a-f]{32}")


class BodyFiles:
    """Immutable files of large response bodies, by ETag, bounded in bytes.

    Parameters
    ----------
    folder : Path
        Where the files live (``<data_dir>/bodies``); created if absent. Files of
        a previous run are kept (a body never changes) and temporary files of
        an interrupted write are removed.
    capacity : int
        Most bytes of files at any time, temporary files included; the least
        recently used are removed to make room, except those being sent.

    A file is written by :func:`~lodserver.io.files.write_atomic` (a temporary
    name, flushed to disk, renamed), so a reader never sees a partial body, even
    after a crash.
    A file being sent is *leased*: eviction skips it, so it is never removed
    between a request finding it and its response opening it.
    """

    def __init__(self, folder: Path, capacity: int):
        self.folder = Path(folder)
        self.capacity = capacity
        self._lock = threading.Lock()
        self._sizes: OrderedDict[str, int] = OrderedDict()    # name -> bytes, LRU first
        self._leases: dict[str, int] = {}
        self._reserved = 0           # bytes of files being written
        self.folder.mkdir(parents=True, exist_ok=True)
        found = []
        for entry in os.scandir(self.folder):
            if entry.name.startswith("."):
                _remove(entry.path)
            elif _NAME.fullmatch(entry.name) and entry.is_file(follow_symlinks=False):
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

    @staticmethod
    def name_of(key: str) -> str:
        name = key.strip('"')
        if not _NAME.fullmatch(name):
            raise ValueError(f"not an ETag of etag_for: {key!r}")
        return name

    def lease(self, key: str) -> tuple[Path, int] | None:
        """(path, bytes) of ``key``'s file, leased until :meth:`release`; None if absent."""
        name = self.name_of(key)
        with self._lock:
            size = self._sizes.get(name)
            if size is None:
                return None
            self._sizes.move_to_end(name)
            self._leases[name] = self._leases.get(name, 0) + 1
        return self.folder / name, size

    def release(self, key: str) -> None:
        name = self.name_of(key)
        with self._lock:
            left = self._leases.pop(name, 0) - 1
            if left > 0:
                self._leases[name] = left

    def store(self, key: str, body: bytes | memoryview) -> bool:
        """Write ``body`` as ``key``'s file; False (nothing written) when it cannot
        be made room for or the write fails (the disk is full, say)."""
        name, size = self.name_of(key), body_size(body)
        with self._lock:
            if name in self._sizes:
                return True
            if not self._make_room(size):
                return False
            self._reserved += size
        written = False
        try:
            write_atomic(self.folder / name, body)     # never a partial body
            written = True
        except OSError as exc:
            log.warning("a response body was not written to the body files: %s", exc)
        finally:
            with self._lock:
                self._reserved -= size
                if written:
                    self._sizes.setdefault(name, size)
        return written

    def _make_room(self, size: int) -> bool:
        """Remove unleased files, least recently used first, until ``size`` more
        bytes fit (with the lock held); False if they cannot."""
        held = sum(self._sizes.values()) + self._reserved
        if held + size <= self.capacity:
            return True
        for name in list(self._sizes):
            if name in self._leases:
                continue
            held -= self._sizes.pop(name)
            _remove(self.folder / name)
            if held + size <= self.capacity:
                return True
        return False


def _remove(path) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    except OSError as exc:
        log.warning("could not remove a body file: %s", exc)


class BodyFileResponse(FileResponse):
    """A body file streamed in 64 KiB reads (Range requests included), its lease
    released when the response is over, sent or not."""

    def __init__(self, files: BodyFiles, key: str, path: Path, *, media_type: str,
                 headers: dict):
        super().__init__(path, media_type=media_type, headers=headers,
                         stat_result=os.stat(path))
        self._files, self._key = files, key

    async def __call__(self, scope, receive, send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._files.release(self._key)
