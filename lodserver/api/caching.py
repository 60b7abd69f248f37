"""Immutable responses: ETags, 304s and a small in-memory cache of encoded bodies.

An artefact never changes once written and ids are never reused, so a level or
a packet is fully named by the artefact's digest and the request's resolved
parameters: that name is the ETag, and the response may be cached for a year.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

from fastapi import Request, Response

from ..packets import PACKET_VERSION

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


def immutable(body: bytes | memoryview | None, *, media_type: str, etag: str,
              filename: str | None = None) -> Response:
    """The response for ``body``, or a 304 when ``body`` is None."""
    headers = {"ETag": etag, "Cache-Control": IMMUTABLE}
    if body is None:
        return Response(status_code=304, headers=headers)
    if filename:
        headers["Content-Disposition"] = f'inline; filename="{filename}"'
    return BufferResponse(body, media_type=media_type, headers=headers)


class BodyCache:
    """A thread-safe LRU of response bodies by ETag, bounded in bytes."""

    def __init__(self, capacity: int = CACHE_BYTES):
        self.capacity = capacity
        self._items: OrderedDict[str, bytes] = OrderedDict()
        self._size = 0
        self._lock = threading.Lock()

    def get_or_make(self, key: str, make) -> bytes:
        with self._lock:
            body = self._items.get(key)
            if body is not None:
                self._items.move_to_end(key)
                return body
        # Encode outside the lock: two racing requests both encode, which is harmless.
        body = make()
        if len(body) <= self.capacity:
            with self._lock:
                if key not in self._items:
                    self._items[key] = body
                    self._size += len(body)
                while self._size > self.capacity:
                    _, dropped = self._items.popitem(last=False)
                    self._size -= len(dropped)
        return body
