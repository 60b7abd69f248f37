"""A TCP proxy on a loopback port in front of a service (PostgreSQL, S3), for
outages a test switches on and off without touching the service itself, which
other tests of the session share.

``refuse()``: the port is closed and every connection through it cut (the
service is down: connections are refused). ``hang()``: connections are accepted
but nothing is forwarded either way (the service is unreachable: packets
dropped). ``restore()``: forwarding again, on the same port.
"""

from __future__ import annotations

import socket
import threading


class TcpProxy:
    """Forwards ``127.0.0.1:<port>`` to ``upstream`` (host, port) until closed."""

    def __init__(self, upstream: tuple[str, int]):
        self.upstream = upstream
        self._lock = threading.Lock()
        self._flowing = threading.Event()
        self._flowing.set()
        self._connections: set[socket.socket] = set()
        self._listener = None
        self.port = self._listen(0)

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    def _listen(self, port: int) -> int:
        listener = socket.socket()
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", port))
        listener.listen(64)
        self._listener = listener
        threading.Thread(target=self._accept, args=(listener,), daemon=True).start()
        return listener.getsockname()[1]

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return                  # closed by refuse() or close()
            try:
                server = socket.create_connection(self.upstream, timeout=10)
                server.settimeout(None)
            except OSError:
                client.close()
                continue
            with self._lock:
                self._connections |= {client, server}
            for source, sink in ((client, server), (server, client)):
                threading.Thread(target=self._pump, args=(source, sink), daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket) -> None:
        try:
            while True:
                self._flowing.wait()
                data = source.recv(65536)
                if not data:
                    break
                self._flowing.wait()        # hang(): held here until restore()
                sink.sendall(data)
        except OSError:
            pass
        finally:
            self._drop(source, sink)

    def _drop(self, *sockets: socket.socket) -> None:
        for sock in sockets:
            with self._lock:
                self._connections.discard(sock)
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()

    def refuse(self) -> None:
        """Close the port and cut every connection."""
        self._flowing.set()
        if self._listener is not None:
            # shutdown first: a close alone leaves the accept() under way listening
            try:
                self._listener.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._listener.close()
            self._listener = None
        with self._lock:
            connections = list(self._connections)
        self._drop(*connections)

    def hang(self) -> None:
        """Accept, but forward nothing until :meth:`restore`."""
        self._flowing.clear()

    def restore(self) -> None:
        """Forward again (reopening the port after :meth:`refuse`)."""
        if self._listener is None:
            self._listen(self.port)
        self._flowing.set()

    def close(self) -> None:
        self.refuse()

    def __enter__(self) -> TcpProxy:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
