"""A real ``lodserver serve`` process on a loopback port, driven over HTTP."""

import time

import numpy as np

from lodserver.packets import apply_packet, state_from_json

from .meshes import DATA
from .server import serve


def test_upload_build_serve_and_stream_packets(tmp_path):
    with serve(tmp_path / "data") as client:
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
    with serve(tmp_path / "data") as client:
        again = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.25, "format": "glb"})
        assert again.status_code == 200 and again.content == glb.content
