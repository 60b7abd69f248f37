"""Faults against a real ``lodserver serve`` process: killed mid-upload, out of
disk space while receiving and while building. Nothing temporary survives a
restart, nothing goes through the system temp directory, and a full disk is
a 507 (or a failure that says so) with the catalogue intact."""

import os
import shutil
import socket
import subprocess
import time
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import pytest

from ..meshes import DATA
from ..server import server_process

SPOT = (DATA / "spot.obj").read_bytes()
BOUNDARY = "lodserver-test-boundary"


def _start_slow_upload(base: str, filename="spot.obj") -> socket.socket:
    """Open a chunked multipart POST /meshes and send its head; the caller sends the rest."""
    where = urlsplit(base)
    sock = socket.create_connection((where.hostname, where.port), timeout=10)
    sock.sendall((f"POST /meshes HTTP/1.1\r\nHost: {where.netloc}\r\n"
                  f"Content-Type: multipart/form-data; boundary={BOUNDARY}\r\n"
                  "Transfer-Encoding: chunked\r\n\r\n").encode())
    _send_chunk(sock, (f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"file\"; "
                       f"filename=\"{filename}\"\r\n\r\n").encode())
    return sock


def _send_chunk(sock, data: bytes) -> None:
    sock.sendall(f"{len(data):x}\r\n".encode() + data + b"\r\n")


def _open_files(pid: int) -> list[str]:
    files = []
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            files.append(os.readlink(fd))
        except OSError:
            pass
    return files


def test_kill_mid_upload_then_restart_leaves_no_temporary_file(tmp_path):
    data, system_tmp = tmp_path / "data", tmp_path / "system-tmp"
    system_tmp.mkdir()
    env = {"TMPDIR": str(system_tmp)}
    with server_process(data, env=env) as (base, process):
        sock = _start_slow_upload(base)
        pad = b"# a slow upload, one line at a time\n" * 1000
        sent = 0
        deadline = time.monotonic() + 30
        partial = []
        while not partial or partial[0].stat().st_size < 2**20:
            assert time.monotonic() < deadline, "the upload never reached data/tmp"
            _send_chunk(sock, pad)
            sent += len(pad)
            time.sleep(0.01)
            partial = list((data / "tmp").glob("upload-*/spot.obj"))
        # the body streams into the data directory as it arrives, no further copy
        # exists, and nothing is open in the system temp dir (not even unlinked)
        assert len(partial) == 1 and partial[0].stat().st_size <= sent
        opened = _open_files(process.pid)
        assert str(partial[0]) in opened
        assert not [f for f in opened if f.startswith(str(system_tmp)) or
                    (f.startswith("/tmp/") and f.endswith("(deleted)"))], opened
        process.kill()
        process.wait()
        sock.close()
    assert list((data / "tmp").rglob("*"))      # the kill left the partial upload
    with server_process(data, env=env) as (base, _):
        assert list((data / "tmp").iterdir()) == []
        assert httpx.get(f"{base}/meshes").json()["meshes"] == []
        # and a normal upload right after works
        with open(DATA / "spot.obj", "rb") as file:
            created = httpx.post(f"{base}/meshes", files={"file": ("spot.obj", file)},
                                 timeout=60)
        assert created.status_code == 202, created.text
    assert list(system_tmp.iterdir()) == []
    assert list((data / "tmp").iterdir()) == []


def test_a_client_that_goes_away_mid_upload_leaves_nothing(tmp_path):
    data = tmp_path / "data"
    with server_process(data) as (base, _):
        sock = _start_slow_upload(base)
        deadline = time.monotonic() + 30
        while not list((data / "tmp").glob("upload-*/spot.obj")):
            assert time.monotonic() < deadline, "the upload never reached data/tmp"
            _send_chunk(sock, b"# more to come\n" * 4096)
            time.sleep(0.01)
        sock.close()
        deadline = time.monotonic() + 30
        while list((data / "tmp").iterdir()):
            assert time.monotonic() < deadline, "the partial upload was not removed"
            time.sleep(0.05)
        assert httpx.get(f"{base}/meshes").json()["meshes"] == []
        assert httpx.get(f"{base}/healthz").json() == {"status": "ok", "ready": True}


def _children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return found


def _grid_stl(path: Path, n: int) -> int:
    """A binary STL of an n x n grid of quads (2 n**2 triangles); its size in bytes."""
    import numpy as np

    x, y = np.meshgrid(np.arange(n + 1, dtype=np.float32), np.arange(n + 1, dtype=np.float32))
    grid = np.stack([x, y, np.sin(x) * np.cos(y)], -1).astype(np.float32)
    a, b, c, d = grid[:-1, :-1], grid[:-1, 1:], grid[1:, 1:], grid[1:, :-1]
    corners = np.concatenate([np.stack([a, b, c], -2).reshape(-1, 3, 3),
                              np.stack([a, c, d], -2).reshape(-1, 3, 3)])
    record = np.zeros(len(corners), dtype=[("normal", "<f4", 3), ("corners", "<f4", (3, 3)),
                                           ("attribute", "<u2")])
    record["corners"] = corners
    path.write_bytes(b"\0" * 80 + np.uint32(len(record)).tobytes() + record.tobytes())
    return path.stat().st_size


def test_kill_mid_parse_then_restart_leaves_nothing(tmp_path):
    """kill -9 while the parse worker reads the upload: the worker does not outlive
    its server for long, and the restart removes the upload's folder."""
    data, system_tmp = tmp_path / "data", tmp_path / "system-tmp"
    system_tmp.mkdir()
    stl = tmp_path / "grid.stl"
    size = _grid_stl(stl, 700)          # ~1M triangles, ~49 MB: a few seconds to parse
    env = {"TMPDIR": str(system_tmp), "LODSERVER_MAX_UPLOAD_BYTES": str(2 * size)}
    with server_process(data, env=env) as (base, process):
        sock = _start_slow_upload(base, "grid.stl")
        with open(stl, "rb") as file:
            while block := file.read(1 << 20):
                _send_chunk(sock, block)
        _send_chunk(sock, f"\r\n--{BOUNDARY}--\r\n".encode())
        sock.sendall(b"0\r\n\r\n")
        deadline = time.monotonic() + 60
        while not _children(process.pid):       # the parse worker has started
            assert time.monotonic() < deadline, "no parse worker started"
            time.sleep(0.05)
        workers = _children(process.pid)
        uploaded = list((data / "tmp").glob("upload-*/grid.stl"))
        assert len(uploaded) == 1 and uploaded[0].stat().st_size == size
        process.kill()
        process.wait()
        sock.close()
    deadline = time.monotonic() + 60
    while any(Path(f"/proc/{pid}").exists() and
              "zombie" not in Path(f"/proc/{pid}/status").read_text() for pid in workers):
        assert time.monotonic() < deadline, "the parse worker outlived its server"
        time.sleep(0.2)
    with server_process(data, env=env) as (base, _):
        assert list((data / "tmp").iterdir()) == []
        assert httpx.get(f"{base}/meshes").json()["meshes"] == []
    assert list(system_tmp.iterdir()) == []


@pytest.fixture
def small_disk(tmp_path):
    """A 6 MB tmpfs, for a server's data directory that really runs out of space."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root and mount(8); "
                    "test_upload_safety simulates a full disk instead")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=6m", "tmpfs", str(disk)],
                          capture_output=True)
    if done.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def _free(path) -> int:
    stat = os.statvfs(path)
    return stat.f_bavail * stat.f_frsize


def _wait(client, mesh_id, timeout=120):
    deadline = time.monotonic() + timeout
    while (body := client.get(f"/meshes/{mesh_id}").json())["status"] not in ("ready", "failed"):
        assert time.monotonic() < deadline
        time.sleep(0.1)
    return body


def _upload(client, content, filename="spot.obj"):
    return client.post("/meshes", files={"file": (filename, content)})


def test_a_full_disk_is_507_and_a_build_without_space_says_so(small_disk, tmp_path):
    data = small_disk / "data"
    with server_process(data) as (base, _), httpx.Client(base_url=base, timeout=60) as client:
        first = _upload(client, SPOT).json()["id"]
        assert _wait(client, first)["status"] == "ready"
        catalogue = client.get("/meshes").json()

        # receiving: an upload larger than the free space
        big = SPOT + b"# padding\n" * ((_free(small_disk) + 2**20) // 10)
        response = _upload(client, big)
        assert response.status_code == 507, response.text
        message = response.json()["message"]
        assert "disk space" in message and str(small_disk) not in message
        assert client.get("/meshes").json() == catalogue
        assert list((data / "tmp").iterdir()) == []
        assert list((data / "sources").iterdir()) == []

        # building: room for the upload, not for its artefact
        stored = sorted(p.name for p in (data / "artefacts").iterdir())
        artefact = (data / "artefacts" / stored[0]).stat().st_size
        assert artefact > 128 * 2**10
        filler = small_disk / "filler"
        with open(filler, "wb") as out:
            out.write(b"\0" * (_free(small_disk) - len(SPOT) - 96 * 2**10))
        created = _upload(client, SPOT)
        assert created.status_code == 202, created.text
        body = _wait(client, created.json()["id"])
        assert body["status"] == "failed", body
        assert body["failure"].startswith("the server ran out of disk space while building")
        assert str(small_disk) not in body["failure"]
        assert sorted(p.name for p in (data / "artefacts").iterdir()) == stored
        assert list((data / "sources").iterdir()) == []
        assert list((data / "tmp").iterdir()) == []
        # what was stored before is still served, and with space back builds work again
        assert client.get(f"/meshes/{first}/lod", params={"ratio": 0.5}).status_code == 200
        filler.unlink()
        again = _upload(client, SPOT).json()["id"]
        assert _wait(client, again)["status"] == "ready"
