"""A real ``lodserver serve`` process on a loopback port, driven over HTTP."""


import numpy as np

from lodserver.packets import apply_packet, state_from_json

from ..meshes import DATA
from ..server import serve, upload_and_wait


def test_upload_build_serve_and_stream_packets(tmp_path):
    with serve(tmp_path / "data") as client:
        mesh_id = upload_and_wait(client, DATA / "spot.obj")["id"]

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
