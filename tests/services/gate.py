"""A TCP gate on loopback in front of a service, for the chaos tests: it forwards
every connection to the service, and on demand

- **cuts the service off** (:meth:`Gate.cut`): open connections are reset and new
  ones are accepted and reset at once, as a firewall or a partition makes a
  service unreachable while it keeps its state (moto keeps its objects in
  memory: stopping it would lose them);
- **holds one answer** (:meth:`Gate.hold_answer_to`): once a client sent a
  request containing given bytes (``PUT /bucket/.../artefacts/`` say), the
  next bytes the service sends back on that connection wait until the test
  releases them (an interim ``100 Continue`` passes). The client is then paused at a known point (its request done
  on the service, its answer not read), observed from outside, without any
  hook in the code under test;
- **stops reading a request** (:meth:`Gate.stall_requests_to`): once a client
  sent bytes containing a pattern, the gate reads nothing more from it and
  forwards nothing, as a store whose disk or network stalls mid-upload does.
  A body larger than the sockets' buffers then blocks the client's writes,
  which a read timeout alone never ends.

One thread per direction per connection; for tests only.
"""

from __future__ import annotations

import socket
import struct
import threading


class Gate:
    """Forward ``127.0.0.1:<port>`` to ``target`` (host, port); see the module docstring."""

    def __init__(self, target: tuple[str, int]):
        self.target = target
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        self._lock = threading.Lock()
        self._open: set[socket.socket] = set()
        self._cut = False
        self._pattern: bytes | None = None
        self._stall: bytes | None = None
        self.seen = threading.Event()        # the held request was sent
        self._release = threading.Event()
        self.refused = 0                     # connections reset while cut off
        threading.Thread(target=self._accept, daemon=True).start()

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def cut(self) -> None:
        """Make the service unreachable: reset every open connection and refuse new ones."""
        with self._lock:
            self._cut = True
            sockets, self._open = list(self._open), set()
        for sock in sockets:
            try:
                sock.shutdown(socket.SHUT_RDWR)     # wakes its pump, which closes it
            except OSError:
                pass

    def restore(self) -> None:
        """Forward again."""
        with self._lock:
            self._cut = False

    def hold_answer_to(self, pattern: bytes) -> None:
        """Hold the answer to the next request containing ``pattern`` (``seen`` is set
        when it went through) until :meth:`release`."""
        with self._lock:
            self._pattern = pattern
            self.seen.clear()
            self._release.clear()

    def stall_requests_to(self, pattern: bytes) -> None:
        """Stop reading from any client that sends ``pattern`` (``seen`` is set when
        one did), until :meth:`release`."""
        with self._lock:
            self._stall = pattern
            self.seen.clear()
            self._release.clear()

    def release(self) -> None:
        with self._lock:
            self._pattern = self._stall = None
        self._release.set()

    def close(self) -> None:
        self.release()
        self.cut()
        self._listener.close()

    # ---- forwarding -----------------------------------------------------------
    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            with self._lock:
                cut = self._cut
                if cut:
                    self.refused += 1
            if cut:
                _reset(client)
                continue
            try:
                server = socket.create_connection(self.target, timeout=10)
                server.settimeout(None)
            except OSError:
                _reset(client)
                continue
            with self._lock:
                self._open.update((client, server))
            held = threading.Event()         # this connection's answer is to be held
            threading.Thread(target=self._pump, args=(client, server, held, True),
                             daemon=True).start()
            threading.Thread(target=self._pump, args=(server, client, held, False),
                             daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket, held: threading.Event,
              asking: bool) -> None:
        tail = b""
        try:
            while data := source.recv(65536):
                if asking:
                    with self._lock:
                        pattern, stall = self._pattern, self._stall
                    if stall and stall in tail + data:
                        self.seen.set()
                        self._release.wait()    # nothing read, nothing forwarded
                    if pattern and not held.is_set() and pattern in tail + data:
                        held.set()
                        self.seen.set()
                    tail = (tail + data)[-256:]
                elif held.is_set():
                    if data.startswith(b"HTTP/1.1 100"):
                        # "100 Continue" asks for the body: passed, or no body is sent
                        end = data.find(b"\r\n\r\n") + 4
                        sink.sendall(data[:end])
                        data = data[end:]
                        if not data:
                            continue
                    self._release.wait()
                    held.clear()
                sink.sendall(data)
        except OSError:
            pass
        finally:
            for sock in (source, sink):
                with self._lock:
                    self._open.discard(sock)
                _reset(sock)


def _reset(sock: socket.socket) -> None:
    """Close with a reset (SO_LINGER 0), as an unreachable peer's firewall does."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    except OSError:
        pass
    sock.close()
