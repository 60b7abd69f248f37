"""Cacheable responses: versions, ETags, 304s, and the two caches of encoded bodies.

An artefact never changes once written, so a level or a packet is fully named
by the artefact's digest and the request's resolved parameters: that name is
the ETag. A URL naming only the mesh id, though, may come to mean other bytes
(the mesh deleted, its id given a new build, or rebuilt), so a shared cache (a
CDN in front of several servers) may keep such a response only briefly
(:data:`REVALIDATE`, then a 304 by ETag). A URL that also names the artefact's
*version* (``v=``, the first :data:`VERSION_DIGITS` hex digits of its SHA-256,
handed out by ``GET /meshes/{id}``) can only ever mean one body: it is served
:data:`IMMUTABLE`, cacheable for a year. A version that is no longer the
mesh's is a 404 that no cache keeps (:func:`cache_control`). Every cacheable
route ends in :func:`respond_cached` (a 304 or the body, with that policy).

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
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

from fastapi import HTTPException, Query, Request, Response
from starlette.responses import FileResponse

from ..packets import PACKET_VERSION
from ..service.lru_folder import LruFolder

log = logging.getLogger(__name__)

IMMUTABLE = "public, max-age=31536000, immutable"
# An unversioned URL: a shared cache may serve it for a minute (so a delete or a
# rebuild shows through a CDN within one), then revalidates it with its ETag.
REVALIDATE_SECONDS = 60
REVALIDATE = f"public, max-age={REVALIDATE_SECONDS}"
# A version is this many hex digits of the artefact's SHA-256 (64 bits: two
# builds of one id sharing a prefix by chance are not a practical concern).
VERSION_DIGITS = 16
VERSION_PATTERN = f"^[0-9a-f]{{{VERSION_DIGITS}}}$"
# Encoded bodies kept in memory, by total size: repeated requests skip the encoder.
CACHE_BYTES = 128 * 2**20


def etag_for(digest: str, *parts) -> str:
    """A strong ETag for the response named by an artefact digest and parameters."""
    name = ":".join(str(part) for part in (digest, PACKET_VERSION, *parts))
    return '"' + hashlib.sha256(name.encode()).hexdigest()[:32] + '"'


def version_of(digest: str | None) -> str | None:
    """The version of an artefact whose SHA-256 is ``digest`` (hex), for ``v=``."""
    return digest[:VERSION_DIGITS] if digest else None


def versioned_urls(mesh_id: str, digest: str | None) -> dict[str, str] | None:
    """The URLs of a ready mesh's level, packet and chain routes and its materials,
    at its artefact's version (a client appends the route's other parameters:
    ``&ratio=0.1``); None without an artefact."""
    version = version_of(digest)
    if version is None:
        return None
    return {route: f"/meshes/{mesh_id}/{route}?v={version}"
            for route in ("lod", "splits", "chain", "materials")}


def cache_control(digest: str, mesh_id: str, version: str | None) -> str:
    """The Cache-Control of a response from the artefact ``digest`` of ``mesh_id``
    asked for at ``version`` (``v=``, or None): :data:`IMMUTABLE` when it names
    that artefact, :data:`REVALIDATE` when absent. A version the mesh no longer
    has is an HTTP 404 marked ``no-store``: its bytes are gone, and a cache must
    not keep the refusal either (the same bytes may be built again)."""
    if version is None:
        return REVALIDATE
    if version == version_of(digest):
        return IMMUTABLE
    raise HTTPException(404, f"mesh {mesh_id} has no version {version!r}; its current "
                        f"version is {version_of(digest)!r}: GET /meshes/{mesh_id} for its "
                        "URLs", headers={"Cache-Control": "no-store"})


VersionQuery = Annotated[str | None, Query(pattern=VERSION_PATTERN, description=(
    f"The artefact's version ({VERSION_DIGITS} hex digits, as GET /meshes/{{id}} hands it out "
    "in its urls): the response is then cacheable for a year; 404 if the mesh no longer has "
    "that version."))]


def load_versioned(store, mesh_id: str, version: str | None):
    """(asset, digest, Cache-Control) of a ready mesh of ``store`` (its
    ``scene.asset.SceneAsset``), ``version`` (the
    request's ``v=``, or None) checked by :func:`cache_control`.

    The row is read before and after the load: when both name one digest, the
    loaded mesh is that artefact (artefact keys name their digest), so neither the
    ETag nor a year-long Cache-Control ever labels another build's bytes. A
    rebuild landing in between is read again."""
    for _ in range(3):
        digest = store.get(mesh_id=mesh_id).digest
        if digest is None:
            store.load(mesh_id=mesh_id)        # not ready: its NotReadyError (409)
        policy = cache_control(digest, mesh_id, version)   # a wrong v: 404, nothing loaded
        asset = store.load(mesh_id=mesh_id)
        if store.get(mesh_id=mesh_id).digest == digest:
            return asset, digest, policy
    raise HTTPException(503, f"mesh {mesh_id} is being rebuilt; retry in a moment",
                        headers={"Retry-After": "1"})


def with_cache_control(response: Response, value: str) -> Response:
    """``response`` with its Cache-Control set to ``value`` (a 304 too: it must
    carry the policy of the response it stands for)."""
    response.headers["Cache-Control"] = value
    return response


def respond_cached(request: Request, etag: str, policy: str,
                   respond: Callable[[], Response]) -> Response:
    """The sequence every cacheable route ends with, once.

    Parameters
    ----------
    request : Request
        The request, whose If-None-Match may already name ``etag``.
    etag : str
        The response's name (:func:`etag_for`).
    policy : str
        Its Cache-Control (:func:`load_versioned`'s, by ``v=``).
    respond : callable
        ``respond() -> Response``: the full response, called only when the
        client does not have it.

    Returns
    -------
    Response
        A 304 when the client has the body, else ``respond()``; either with
        Cache-Control ``policy`` (a 304 stands for the response it validates).
    """
    if is_fresh(request, etag):
        return with_cache_control(Response(status_code=304, headers=immutable_headers(etag)),
                                  policy)
    return with_cache_control(respond(), policy)


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


def immutable(body: bytes | memoryview, *, media_type: str, etag: str,
              filename: str | None = None) -> Response:
    """The response for ``body``, named ``etag`` and cacheable for a year."""
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
    between a request finding it and its response opening it. The folder is a
    :class:`~lodserver.service.lru_folder.LruFolder`, as the artefact cache's is.
    """

    def __init__(self, folder: Path, capacity: int):
        self.folder = Path(folder)
        self.capacity = capacity
        self._files = LruFolder(self.folder, capacity, names=_NAME, what="body file")

    @property
    def size(self) -> int:
        """Bytes held now (files and writes under way)."""
        return self._files.size

    @staticmethod
    def name_of(key: str) -> str:
        name = key.strip('"')
        if not _NAME.fullmatch(name):
            raise ValueError(f"not an ETag of etag_for: {key!r}")
        return name

    def lease(self, key: str) -> tuple[Path, int] | None:
        """(path, bytes) of ``key``'s file, leased until :meth:`release`; None if absent."""
        return self._files.lease(self.name_of(key))

    def release(self, key: str) -> None:
        self._files.release(self.name_of(key))

    def store(self, key: str, body: bytes | memoryview) -> bool:
        """Write ``body`` as ``key``'s file; False (nothing written) when it cannot
        be made room for or the write fails (the disk is full, say)."""
        try:
            return self._files.write(self.name_of(key), body)
        except OSError as exc:
            log.warning("a response body was not written to the body files: %s", exc)
            return False


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
