"""A real ``lodserver serve`` process on a loopback port, for the tests that
talk to one over HTTP (server process, viewer) and for the benchmarks that
load one (``bench/load.py``, ``bench/viewer/run.py``)."""

import os
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import httpx

from tests.services.processes import stop_processes


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def server_process(data_dir, *, log: Path | None = None, warm_kernels: bool = False,
                   timeout: float = 60, env: dict | None = None, cwd: Path | None = None):
    """Run ``lodserver serve`` on a free loopback port, storing in ``data_dir``;
    yield (base URL, process) once ``/healthz`` answers, stop it on exit.

    ``env`` adds environment variables (``LODSERVER_*`` settings, ``TMPDIR``).
    ``cwd`` is the server's working directory, which ``python -m`` puts first
    on ``sys.path``: a checkout there serves its own package.

    Its output goes to ``log`` (a file path) or is kept for the error message.
    ``warm_kernels`` compiles the kernels at start-up, as a deployed server
    does; tests skip it. Raises RuntimeError if the server does not start
    within ``timeout`` seconds.
    """
    port = _free_port()
    # the interpreter running the caller, not whatever `lodserver` is first on PATH
    command = [sys.executable, "-m", "lodserver.cli", "serve", "--data", str(data_dir),
               "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"]
    env = {**os.environ, "LODSERVER_TOKEN": "",
           "LODSERVER_WARM_KERNELS": "true" if warm_kernels else "false", **(env or {})}
    if log is None:
        process = subprocess.Popen(command, cwd=cwd, env=env, stdout=subprocess.PIPE,
                                   stderr=subprocess.STDOUT)
    else:
        with open(log, "wb") as out:
            process = subprocess.Popen(command, cwd=cwd, env=env, stdout=out,
                                       stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + timeout
        while True:
            try:
                if httpx.get(f"{base}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if process.poll() is not None or time.monotonic() > deadline:
                if log is not None:
                    raise RuntimeError(f"lodserver serve did not start; see {log}")
                out = process.stdout.read().decode(errors="replace") if process.stdout else ""
                raise RuntimeError(f"lodserver serve did not start: {out[-2000:]}")
            time.sleep(0.2)
        yield base, process
    finally:
        stop_processes([process], grace=30)


@contextmanager
def serve(data_dir, *, timeout: float = 60, **options):
    """An httpx client for :func:`server_process` (same options)."""
    with server_process(data_dir, timeout=timeout, **options) as (base, _), \
            httpx.Client(base_url=base, timeout=timeout) as client:
        yield client


def upload(client, name: str, content) -> str:
    """``POST /meshes`` of ``content`` (bytes or a binary file) named ``name``
    through ``client`` (httpx's or FastAPI's TestClient); the new mesh's id. The
    answer must be a 202."""
    created = client.post("/meshes", files={"file": (name, content)})
    assert created.status_code == 202, created.text
    return created.json()["id"]


def wait_ready(client, mesh_id: str, timeout: float = 120) -> dict:
    """Poll ``GET /meshes/{mesh_id}`` until the mesh is ready (a failed build, or
    none ready within ``timeout`` seconds, fails the test); that body."""
    deadline = time.monotonic() + timeout
    while (body := client.get(f"/meshes/{mesh_id}").json())["status"] != "ready":
        assert body["status"] != "failed", body["failure"]
        assert time.monotonic() < deadline, f"the build did not finish in {timeout:g} s"
        time.sleep(0.2)
    return body


def upload_and_wait(client, path):
    """Upload ``path`` through ``client`` and wait (up to 2 min) until it is built;
    its ``GET /meshes/{id}`` body."""
    with open(path, "rb") as file:
        mesh_id = upload(client, path.name, file)
    return wait_ready(client, mesh_id)
