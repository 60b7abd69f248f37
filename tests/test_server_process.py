"""A real ``lodserver serve`` process on a loopback port, driven over HTTP."""

import os
import socket
import subprocess
import sys
import time
from contextlib import contextmanager

import httpx
import numpy as np
import pytest

from lodserver.packets import apply_packet, state_from_json

from .meshes import DATA


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def _serve(data_dir):
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


def test_upload_build_serve_and_stream_packets(tmp_path):
    with _serve(tmp_path / "data") as client:
        with open(DATA / "spot.obj", "rb") as file:
            created = client.post("/meshes", files={"file": ("spot.obj", file)})
        assert created.status_code == 202, created.text
        mesh_id = created.json()["id"]
        deadline = time.monotonic() + 120
        while (body := client.get(f"/meshes/{mesh_id}").json())["status"] != "ready":
            assert body["status"] != "failed", body["failure"]
            assert time.monotonic() < deadline, "the build did not finish"
            time.sleep(0.2)

        def lod(vertices):
            response = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": vertices})
            assert response.status_code == 200
            return state_from_json(response.json())

        def packet(a, b):
            response = client.get(f"/meshes/{mesh_id}/splits", params={"from": a, "to": b})
            assert response.status_code == 200
            assert response.headers["content-type"] == "application/octet-stream"
            return response.content

        levels = [50, 1200, 2930, 300, 50]
        state = lod(levels[0])
        for level in levels[1:]:
            state = apply_packet(state, packet(state.level, level))
            expected = lod(level)
            assert np.array_equal(state.positions, expected.positions)
            assert np.array_equal(state.faces, expected.faces)
        glb = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.25, "format": "glb"})
        assert glb.status_code == 200 and glb.content[:4] == b"glTF"

    # the server stopped; a new one on the same data serves the same bytes
    with _serve(tmp_path / "data") as client:
        again = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.25, "format": "glb"})
        assert again.status_code == 200 and again.content == glb.content
