"""A real ``lodserver serve`` process on a loopback port, for the tests that
talk to one over HTTP (server process, viewer)."""

import os
import socket
import subprocess
import sys
import time
from contextlib import contextmanager

import httpx
import pytest


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def serve(data_dir):
    """An httpx client for a ``lodserver serve`` on a free loopback port, storing
    in ``data_dir``; the process is stopped on exit."""
    port = _free_port()
    # the interpreter running the tests, not whatever `lodserver` is first on PATH
    command = [sys.executable, "-m", "lodserver.cli", "serve", "--data", str(data_dir),
               "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"]
    env = {**os.environ, "LODSERVER_TOKEN": "", "LODSERVER_WARM_KERNELS": "false"}
    process = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{base}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if process.poll() is not None or time.monotonic() > deadline:
                out = process.stdout.read().decode(errors="replace") if process.stdout else ""
                pytest.fail(f"lodserver serve did not start: {out[-2000:]}")
            time.sleep(0.2)
        with httpx.Client(base_url=base, timeout=60) as client:
            yield client
    finally:
        process.terminate()
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
