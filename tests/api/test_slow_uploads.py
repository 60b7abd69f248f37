"""Slow and idle upload bodies, and request heads that never complete, against a
real ``lodserver serve`` process: a
client that sends its headers and then nothing, and one that trickles bytes,
are both cut (408, the connection closed) and leave nothing in ``tmp/``; past
``LODSERVER_CONCURRENT_UPLOADS`` bodies at once, an upload is a 503 with
Retry-After. The settings are small here; the assertions only say "cut
eventually, within a generous deadline", never how fast."""

import socket
import time
from urllib.parse import urlsplit

import httpx

from ..meshes import DATA
from ..server import server_process

SPOT = (DATA / "spot.obj").read_bytes()
BOUNDARY = "lodserver-test-boundary"
# How long any cut may take on a loaded machine: far above the settings used.
DEADLINE = 60.0


def _open_upload(base: str, *, length: int = 10 * 2**20) -> socket.socket:
    """Send the head of a POST /meshes declaring ``length`` body bytes, and nothing else."""
    where = urlsplit(base)
    sock = socket.create_connection((where.hostname, where.port), timeout=DEADLINE)
    sock.sendall((f"POST /meshes HTTP/1.1\r\nHost: {where.netloc}\r\n"
                  f"Content-Type: multipart/form-data; boundary={BOUNDARY}\r\n"
                  f"Content-Length: {length}\r\n\r\n").encode())
    return sock


def _part_head(filename="spot.obj") -> bytes:
    return (f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"file\"; "
            f"filename=\"{filename}\"\r\n\r\n").encode()


def _answer_or_close(sock: socket.socket, deadline: float) -> bytes:
    """What the server sends until it closes the connection (b"" if it only closed it)."""
    received = b""
    sock.settimeout(1.0)
    while time.monotonic() < deadline:
        try:
            data = sock.recv(65536)
        except socket.timeout:
            continue
        except ConnectionResetError:
            return received
        if not data:
            return received
        received += data
    raise AssertionError(f"the connection was still open after {DEADLINE} s: {received!r}")


def _wait_until(condition, what: str, timeout: float = DEADLINE) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def _uploads_in(data) -> list:
    return list((data / "tmp").glob("upload-*"))


def test_an_upload_that_stops_after_its_headers_is_cut_and_removed(tmp_path):
    data = tmp_path / "data"
    env = {"LODSERVER_UPLOAD_IDLE_SECONDS": "1"}
    with server_process(data, env=env) as (base, _):
        sock = _open_upload(base)
        try:
            _wait_until(lambda: _uploads_in(data), "the upload never reached data/tmp")
            answer = _answer_or_close(sock, time.monotonic() + DEADLINE)
        finally:
            sock.close()
        assert answer == b"" or answer.startswith(b"HTTP/1.1 408"), answer
        assert b"sent nothing for 1 seconds" in answer or answer == b""
        _wait_until(lambda: not list((data / "tmp").iterdir()),
                    "the stalled upload's folder was not removed")
        assert httpx.get(f"{base}/meshes").json()["meshes"] == []


def test_a_trickling_upload_is_cut_by_the_minimum_rate(tmp_path):
    data = tmp_path / "data"
    # the idle limit alone would never cut this client: it sends every 0.2 s
    env = {"LODSERVER_UPLOAD_IDLE_SECONDS": "30", "LODSERVER_UPLOAD_MIN_RATE": "1000",
           "LODSERVER_UPLOAD_RATE_SECONDS": "1"}
    with server_process(data, env=env) as (base, _):
        sock = _open_upload(base)
        try:
            sock.sendall(_part_head())
            _wait_until(lambda: _uploads_in(data), "the upload never reached data/tmp")
            deadline = time.monotonic() + DEADLINE
            sent, cut = 0, False
            while not cut:
                assert time.monotonic() < deadline, f"a trickle of {sent} bytes was not cut"
                try:
                    sock.sendall(SPOT[sent % len(SPOT):][:8])
                    sent += 8
                except (BrokenPipeError, ConnectionResetError):
                    cut = True
                    break
                sock.settimeout(0.2)
                try:
                    data_back = sock.recv(65536)
                except socket.timeout:
                    continue
                except ConnectionResetError:
                    cut = True
                    break
                assert data_back == b"" or data_back.startswith(b"HTTP/1.1 408"), data_back
                cut = True
        finally:
            sock.close()
        _wait_until(lambda: not list((data / "tmp").iterdir()),
                    "the trickling upload's folder was not removed")
        assert httpx.get(f"{base}/meshes").json()["meshes"] == []
        # a normal upload is still taken at once
        created = httpx.post(f"{base}/meshes", files={"file": ("spot.obj", SPOT)}, timeout=60)
        assert created.status_code == 202, created.text


def test_uploads_past_the_concurrent_limit_are_503_with_retry_after(tmp_path):
    data = tmp_path / "data"
    env = {"LODSERVER_CONCURRENT_UPLOADS": "2", "LODSERVER_UPLOAD_IDLE_SECONDS": "120",
           "LODSERVER_UPLOAD_MIN_RATE": "0"}
    with server_process(data, env=env) as (base, _):
        stalled = [_open_upload(base) for _ in range(2)]
        try:
            _wait_until(lambda: len(_uploads_in(data)) == 2,
                        "the two stalled uploads never reached data/tmp")
            refused = httpx.post(f"{base}/meshes", files={"file": ("spot.obj", SPOT)},
                                 timeout=60)
            assert refused.status_code == 503, refused.text
            assert int(refused.headers["Retry-After"]) > 0
            assert "receiving 2 uploads" in refused.json()["message"]
            assert len(_uploads_in(data)) == 2      # the refused body was never stored
        finally:
            for sock in stalled:
                sock.close()
        # the slots come back once the clients are gone
        _wait_until(lambda: not list((data / "tmp").iterdir()),
                    "the abandoned uploads' folders were not removed")
        created = httpx.post(f"{base}/meshes", files={"file": ("spot.obj", SPOT)}, timeout=60)
        assert created.status_code == 202, created.text


def test_a_request_whose_headers_trickle_is_answered_408_and_closed(tmp_path):
    """uvicorn bounds the wait between kept-alive requests, not the arrival of a
    request's head: without lodserver's deadline (api/protocol.py) each of these
    connections would be held for ever."""
    env = {"LODSERVER_HEADER_SECONDS": "1"}
    with server_process(tmp_path / "data", env=env) as (base, _):
        where = urlsplit(base)
        silent = socket.create_connection((where.hostname, where.port), timeout=DEADLINE)
        trickling = socket.create_connection((where.hostname, where.port), timeout=DEADLINE)
        kept = socket.create_connection((where.hostname, where.port), timeout=DEADLINE)
        try:
            # a whole first request on a kept-alive connection is answered as usual
            kept.sendall(f"GET /meshes HTTP/1.1\r\nHost: {where.netloc}\r\n\r\n".encode())
            first = kept.recv(65536)
            head, _, body = first.partition(b"\r\n\r\n")
            length = int(next(line.split(b":")[1] for line in head.split(b"\r\n")
                              if line.lower().startswith(b"content-length:")))
            while len(body) < length:
                body += kept.recv(65536)
            assert first.startswith(b"HTTP/1.1 200") and len(body) == length, first
            kept.sendall(b"GET /meshes HTTP/1.1\r\n")      # its next request stops halfway
            trickling.sendall(f"GET /meshes HTTP/1.1\r\nHost: {where.netloc}\r\n".encode())
            deadline = time.monotonic() + DEADLINE
            trickled = 0
            while trickled < 40 and time.monotonic() < deadline:
                try:
                    trickling.sendall(b"X")                 # one header byte at a time
                except (BrokenPipeError, ConnectionResetError):
                    break
                trickled += 1
                time.sleep(0.25)
            for sock in (silent, trickling, kept):
                answer = _answer_or_close(sock, deadline)
                assert answer == b"" or answer.startswith(b"HTTP/1.1 408"), answer
                assert answer == b"" or b"did not arrive in time" in answer
            assert trickled < 40, "the trickling head was never cut"
        finally:
            for sock in (silent, trickling, kept):
                sock.close()
        # the server still answers whole requests
        assert httpx.get(f"{base}/meshes").status_code == 200
