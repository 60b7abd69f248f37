"""uvicorn's HTTP protocol with a deadline on each request's head.

uvicorn bounds the wait between requests of a kept-alive connection
(``timeout_keep_alive``) but not the arrival of a request line and its
headers: a client that opens connections and sends their headers a byte at a
time ("slowloris") holds each one for ever, and enough of them exhaust the
server's sockets before any request reaches the app, where every other limit
lives. Here each request's head must arrive within ``header_seconds`` of its
connection's opening or of its first byte, or the connection is answered 408
and closed. Bodies are the app's to bound (uploads: ``upload_idle_seconds``,
``upload_min_rate``).
"""

from __future__ import annotations

import asyncio

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

_BODY = b'{"message":"the request\'s headers did not arrive in time."}'
_TIMEOUT_ANSWER = (b"HTTP/1.1 408 Request Timeout\r\nconnection: close\r\n"
                   b"content-type: application/json\r\n"
                   b"content-length: %d\r\n\r\n%s" % (len(_BODY), _BODY))


class HeadDeadlineProtocol(HttpToolsProtocol):
    """:class:`HttpToolsProtocol` whose request heads have a deadline (module docstring)."""

    header_seconds: float = 10.0
    _head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._head_timer = self.loop.call_later(self.header_seconds, self._head_late)

    def on_message_begin(self) -> None:
        super().on_message_begin()
        if self._head_timer is None:     # a later request on a kept-alive connection
            self._head_timer = self.loop.call_later(self.header_seconds, self._head_late)

    def on_headers_complete(self) -> None:
        self._cancel_head_timer()
        super().on_headers_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        super().connection_lost(exc)

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_late(self) -> None:
        self._head_timer = None
        if not self.transport.is_closing():
            self.transport.write(_TIMEOUT_ANSWER)
            self.transport.close()


def head_deadline_protocol(header_seconds: float) -> type[HeadDeadlineProtocol]:
    """The protocol class for uvicorn's ``http=``, with this deadline (seconds)."""
    return type("HeadDeadlineProtocol", (HeadDeadlineProtocol,),
                {"header_seconds": float(header_seconds)})
