"""How a read request gets its body: from memory, from a body file, or encoded
under the heavy-request limit.

Encoding is what costs memory, and an encoder's peak is a small multiple of the
body it makes (the level's arrays, the format's pieces, then the joined body).
What a body weighs is therefore its estimated size in bytes
(``service.levels``: ``level_bytes``, ``packet_bytes``, ``chain_bytes``,
``scene_bytes``), from counts, attribute widths and, for a scene, the bytes it
carries as they are (animations, skins, instancing), never from faces alone. So

1. a body already in the memory cache or in a body file is sent at once, never
   waiting for anything;
2. otherwise one request per body encodes it (the others asking for the same
   body wait for that one, up to ``heavy_wait_seconds``, instead of encoding it
   again), holding ``ceil(estimate / heavy_slot_bytes)`` slots of a
   :class:`HeavyLimit` of ``heavy_requests`` slots, at most all of them. A request
   that cannot get its slots within ``heavy_wait_seconds`` is answered 503 with
   ``Retry-After``;
3. a body above ``body_file_bytes`` is written to a body file, dropped from
   memory (and the freed heap given back to the system, :func:`trim_memory`), and
   streamed from the file; smaller ones go to the memory cache.

A body estimated at no more than ``heavy_slot_bytes / LIGHT_SHARE`` (light work:
small levels and chains, packets cut from prepared records) is made without the
limit. Reads therefore encode at once bodies of at most ``heavy_requests *
heavy_slot_bytes`` estimated bytes in all, or one larger body alone, plus the
light work of the requests in flight; encoder memory is that times the
encoders' peak factor, plus the memory cache (128 MiB). That holds for a scene
whatever its triangle count: a level of a few triangles carrying hundreds of
megabytes of animation weighs those megabytes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import math
import threading
import time
from contextlib import contextmanager
from typing import Annotated, Callable

from fastapi import Depends, FastAPI, HTTPException, Request, Response

from .caching import (BodyCache, BodyFileResponse, BodyFiles, BufferResponse, body_size,
                      immutable_headers, respond_cached)
from .headers import add_security_headers

log = logging.getLogger(__name__)

# A body of at most a slot's 1/LIGHT_SHARE is light work, made without the limit:
# at the default 64 MiB slots, 2 MiB (the json form of about 60k faces).
LIGHT_SHARE = 32


class ServerBusy(HTTPException):
    """503: the slots for encoding were all taken for longer than the wait."""

    def __init__(self, retry_after: float):
        super().__init__(503, "the server is busy encoding other large responses; "
                              "retry in a moment", headers={"Retry-After": str(retry_after)})


class HeavyLimit:
    """At most ``slots`` slots of ``slot_bytes`` bytes of encoding held at once.

    A weighted counter rather than a ``BoundedSemaphore``: a large body takes
    several slots at once, and taking several slots of a semaphore one by one
    lets two such bodies each hold some and wait for the other until both time out.

    Parameters
    ----------
    slots : int
        ``heavy_requests``.
    slot_bytes : int
        ``heavy_slot_bytes``: the estimated body bytes one slot stands for.
    """

    def __init__(self, slots: int, slot_bytes: int = 64 * 2**20):
        if slots < 1:
            raise ValueError(f"heavy_requests must be at least 1, got {slots}")
        if slot_bytes < 1:
            raise ValueError(f"heavy_slot_bytes must be at least 1, got {slot_bytes}")
        self.slots, self.slot_bytes = slots, slot_bytes
        self._free = slots
        self._changed = threading.Condition()

    @property
    def budget(self) -> int:
        """Estimated body bytes all slots stand for: a body this large takes them all."""
        return self.slots * self.slot_bytes

    def weight(self, estimate: int) -> int:
        """Slots for a body of ``estimate`` bytes: 0 (light) up to a slot's
        1/:data:`LIGHT_SHARE`, else one per ``slot_bytes`` begun, at most all."""
        if estimate <= self.slot_bytes // LIGHT_SHARE:
            return 0
        return min(self.slots, -(-int(estimate) // self.slot_bytes))

    @property
    def free(self) -> int:
        with self._changed:
            return self._free

    @contextmanager
    def hold(self, weight: int = 1, *, timeout: float):
        """Hold ``weight`` slots (at most all of them) for the ``with`` block;
        :class:`ServerBusy` if they are not free within ``timeout`` seconds."""
        weight = max(1, min(weight, self.slots))
        deadline = time.monotonic() + timeout
        with self._changed:
            while self._free < weight:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise ServerBusy(_retry_after(timeout))
                self._changed.wait(remaining)
            self._free -= weight
        try:
            yield
        finally:
            with self._changed:
                self._free += weight
                self._changed.notify_all()


def _retry_after(wait: float) -> int:
    return max(1, math.ceil(wait))


def _find_malloc_trim():
    """glibc's ``malloc_trim``, or None (musl, macOS, Windows)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        function = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    function.argtypes, function.restype = [ctypes.c_size_t], ctypes.c_int
    return function


_malloc_trim = _find_malloc_trim()


def trim_memory() -> None:
    """Give freed heap memory back to the system (glibc only; a no-op elsewhere).

    After a large body is written and freed, the encoder's arrays stay in
    glibc's arenas: the process keeps about the encoder's peak memory that it
    no longer uses. ``malloc_trim(0)``, cheap beside the encoding, hands it
    back to the system.
    """
    if _malloc_trim is not None:
        _malloc_trim(0)


class Bodies:
    """The bodies of immutable responses: memory cache, body files, heavy limit.

    Parameters
    ----------
    state : the app's ``state``; its ``cache`` (a :class:`BodyCache`) is opened by
        the lifespan, after this object is made.
    files : BodyFiles
    heavy : HeavyLimit
    file_above : int
        Bodies of more bytes are written to ``files`` and streamed from there.
    wait : float
        Seconds a request may wait for slots (or for another request encoding
        the same body) before it is answered 503.
    """

    def __init__(self, state, files: BodyFiles, heavy: HeavyLimit, *, file_above: int,
                 wait: float):
        self._state, self.files, self.heavy = state, files, heavy
        self.file_above, self.wait = file_above, wait
        self._flights: dict[str, threading.Event] = {}
        self._lock = threading.Lock()

    @property
    def memory(self) -> BodyCache:
        return self._state.cache

    def respond(self, key: str, make: Callable[[], bytes | memoryview], *, media_type: str,
                estimate: Callable[[], int], filename: str | None = None) -> Response:
        """The response for the body named ``key`` (an ETag), made by ``make()``
        unless a cache has it. ``estimate()``: the body's estimated bytes, asked
        only when it must be made; they set the slots ``make`` holds
        (:meth:`HeavyLimit.weight`; 0: light work, done at once)."""
        headers = immutable_headers(key, filename)
        deadline = time.monotonic() + self.wait
        weight = None
        while True:
            found = self._cached(key, media_type, headers)
            if found is not None:
                return found
            if weight is None:
                weight = self.heavy.weight(estimate())
            if weight <= 0:
                return self._keep(key, make, media_type, headers)
            flight, leading = self._join(key)
            if not leading:
                # another request is encoding this body: wait for it, not for a slot
                if not flight.wait(max(0.0, deadline - time.monotonic())):
                    raise ServerBusy(_retry_after(self.wait))
                continue        # it is cached now, unless that request failed
            try:
                with self.heavy.hold(weight, timeout=deadline - time.monotonic()):
                    return self._keep(key, make, media_type, headers)
            finally:
                self._leave(key, flight)

    def cached(self, request: Request, etag: str, policy: str,
               make: Callable[[], bytes | memoryview], *, media_type: str,
               estimate: Callable[[], int], filename: str | None = None) -> Response:
        """A cacheable route's response: a 304 when the client has ``etag``, else
        :meth:`respond`; with Cache-Control ``policy`` (``caching.respond_cached``)."""
        return respond_cached(request, etag, policy, lambda: self.respond(
            etag, make, media_type=media_type, estimate=estimate, filename=filename))

    def _cached(self, key: str, media_type: str, headers: dict) -> Response | None:
        body = self.memory.get(key)
        if body is not None:
            return BufferResponse(body, media_type=media_type, headers=headers)
        leased = self.files.lease(key)
        if leased is None:
            return None
        try:
            return BodyFileResponse(self.files, key, leased[0], media_type=media_type,
                                    headers=headers)
        except OSError:             # removed behind our back: encode it again
            self.files.release(key)
            return None

    def _keep(self, key: str, make, media_type: str, headers: dict) -> Response:
        # make() is called here so that ``body`` is the only reference to it
        body = make()
        if body_size(body) > self.file_above:
            if self.files.store(key, body):
                found = self._cached(key, media_type, headers)
                if found is not None:
                    del body            # the only reference: the body leaves memory here
                    trim_memory()
                    return found
        else:
            self.memory.put(key, body)
        return BufferResponse(body, media_type=media_type, headers=headers)

    def _join(self, key: str) -> tuple[threading.Event, bool]:
        with self._lock:
            flight = self._flights.get(key)
            if flight is not None:
                return flight, False
            flight = self._flights[key] = threading.Event()
            return flight, True

    def _leave(self, key: str, flight: threading.Event) -> None:
        with self._lock:
            self._flights.pop(key, None)
        flight.set()


def get_bodies(request: Request) -> Bodies:
    return request.app.state.bodies


BodiesDep = Annotated[Bodies, Depends(get_bodies)]


def add_bounded_reads(app: FastAPI, settings) -> None:
    """Body files, the heavy-request limit and the security headers, for ``app``."""
    files = BodyFiles(settings.data_dir / "bodies", settings.body_cache_bytes)
    app.state.bodies = Bodies(app.state, files,
                              HeavyLimit(settings.heavy_requests, settings.heavy_slot_bytes),
                              file_above=settings.body_file_bytes,
                              wait=settings.heavy_wait_seconds)
    add_security_headers(app, settings)
