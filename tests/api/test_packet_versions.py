"""Packet version 4 over HTTP: ``/splits?version=4`` answers the bytes of
``encode_packet_v4`` for the same range, with its own ETag, the same limits and
errors as version 3; the summary lists the versions the server writes."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.settings import Settings
from lodserver.packets import apply_packet, decode_any, encode_packet_v4, state_from_json

from ..meshes import DATA
from ..packets.test_packets import _same
from . import uploaded


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """spot (UV, a material) uploaded and built."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("v4") / "data", warm_kernels=False)
    with TestClient(create_app(settings)) as client:
        yield client, uploaded(client, "spot.obj", (DATA / "spot.obj").read_bytes())


def test_the_summary_lists_the_versions_written(served):
    client, mesh_id = served
    body = client.get(f"/meshes/{mesh_id}").json()
    assert body["packet_versions"] == [3, 4]
    assert body["parts"][0]["packet_versions"] == [3, 4]


@pytest.mark.parametrize("start, stop", [(100, 2930), (2930, 100), (500, 1700), (1700, 1699),
                                         (900, 900)])
def test_version_4_is_the_encoder_bytes_and_applies_exactly(served, start, stop):
    client, mesh_id = served
    pm = client.app.state.store.load(mesh_id=mesh_id).single
    params = {"from": start, "to": stop, "version": 4}
    response = client.get(f"/meshes/{mesh_id}/splits", params=params)
    assert response.status_code == 200, response.text
    assert response.content == encode_packet_v4(pm, start, stop)
    assert response.content[4] == 4 and decode_any(response.content) is not None
    # a part's route answers the same bytes
    part = client.get(f"/meshes/{mesh_id}/parts/0/splits", params=params)
    assert part.content == response.content and part.headers["etag"] == response.headers["etag"]
    level = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": start, "format": "json"})
    state = apply_packet(state_from_json(level.json()), decode_any(response.content))
    after = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": stop, "format": "json"})
    _same(state, state_from_json(after.json()))


def test_version_3_stays_the_default_with_its_own_etag(served):
    client, mesh_id = served
    params = {"from": 200, "to": 800}
    default = client.get(f"/meshes/{mesh_id}/splits", params=params)
    three = client.get(f"/meshes/{mesh_id}/splits", params={**params, "version": 3})
    four = client.get(f"/meshes/{mesh_id}/splits", params={**params, "version": 4})
    assert default.content[4] == 3 and four.content[4] == 4
    assert default.content == three.content and default.headers["etag"] == three.headers["etag"]
    assert four.headers["etag"] != default.headers["etag"]
    again = client.get(f"/meshes/{mesh_id}/splits", params={**params, "version": 4},
                       headers={"If-None-Match": four.headers["etag"]})
    assert again.status_code == 304


@pytest.mark.parametrize("params, phrase", [
    ({"from": 100, "to": 200, "version": 5}, "version"),
    ({"from": 100, "to": 200, "version": 2}, "version"),
    ({"from": 1, "to": 200, "version": 4}, "from must be a level"),
    ({"from": 100, "to": 99999, "version": 4}, "to must be a level"),
    ({"from": 100, "to": 200, "version": 4, "bits": 40}, "bits"),
])
def test_version_4_refuses_bad_input_as_version_3_does(served, params, phrase):
    client, mesh_id = served
    response = client.get(f"/meshes/{mesh_id}/splits", params=params)
    assert response.status_code == 422, response.text
    assert phrase in response.text
    assert "/work" not in response.text and "/tmp" not in response.text


def test_version_4_at_another_grid_applies_exactly(served):
    client, mesh_id = served
    pm = client.app.state.store.load(mesh_id=mesh_id).single
    params = {"from": 300, "to": 1200, "bits": 11, "version": 4}
    response = client.get(f"/meshes/{mesh_id}/splits", params=params)
    assert response.content == encode_packet_v4(pm, 300, 1200, bits=11)
    level = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": 300, "format": "json",
                                                          "bits": 11}).json()
    after = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": 1200, "format": "json",
                                                          "bits": 11}).json()
    _same(apply_packet(state_from_json(level), decode_any(response.content)),
          state_from_json(after))
