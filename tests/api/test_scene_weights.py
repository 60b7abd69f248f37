"""Scene levels and chains weighed by their estimated bytes, through the real app: a
scene of a few triangles carrying a large animation takes heavy slots by those
bytes (api/bodies.py), so concurrent ones past the budget get 503 with
Retry-After, while small bodies stay light."""

from __future__ import annotations

import threading

import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.routes import lods
from lodserver.api.settings import Settings
from lodserver.service.levels import carried_bytes, level_bytes, scene_bytes
from lodserver.scene.asset import SceneAsset, scene_levels_for

from ..hostile_files import animated_glb
from ..server import upload, wait_ready

KEYS = 60_000                   # 1.2 MB of keyframes: 20 bytes each with its time
SLOT = 256 * 1024               # so a scene level weighs more than both slots


def _app(data_dir, **settings):
    return TestClient(create_app(Settings(data_dir=data_dir, warm_kernels=False,
                                          heavy_wait_seconds=0.2, **settings)))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A data dir holding the animated grid, built once; (data dir, mesh id)."""
    data = tmp_path_factory.mktemp("scene") / "data"
    with _app(data) as client:
        mesh_id = upload(client, "animated.glb", animated_glb(KEYS))
        wait_ready(client, mesh_id, timeout=180)
    return data, mesh_id


def _lod(client, mesh_id, ratio):
    return client.get(f"/meshes/{mesh_id}/lod", params={"ratio": ratio, "format": "glb"})


def test_a_scene_level_weighs_its_carried_bytes_not_its_triangles(scene):
    data, mesh_id = scene
    with _app(data, heavy_requests=2, heavy_slot_bytes=SLOT) as client:
        asset = client.app.state.store.load(mesh_id=mesh_id)
        assert isinstance(asset, SceneAsset)
        levels = scene_levels_for(asset, ratio=1.0)
        assert sum(asset.pms[p].faces_at_level(v) for p, v in levels.items()) <= 200
        estimate = scene_bytes(asset, [levels])
        assert estimate >= carried_bytes(asset.scene.carried) >= 20 * KEYS
        body = _lod(client, mesh_id, 1.0)
        assert body.status_code == 200
        # the estimate is of the body's size (the animation written as it is)
        assert len(body.content) <= estimate <= 1.5 * len(body.content)
        assert client.app.state.bodies.heavy.weight(estimate) == 2      # every slot


def test_concurrent_scene_levels_past_the_budget_are_503(scene, monkeypatch):
    """One scene level being encoded holds every slot (its bytes): a second, distinct
    level and the chain are 503 with Retry-After meanwhile; a small part level is
    light and is served; once the first is done, slots are free again."""
    data, mesh_id = scene
    entered, release = threading.Event(), threading.Event()
    real = lods.scene_glb

    def held(*args, **kwargs):
        entered.set()
        assert release.wait(60), "the test never released the encoder"
        return real(*args, **kwargs)

    monkeypatch.setattr(lods, "scene_glb", held)
    with _app(data, heavy_requests=2, heavy_slot_bytes=SLOT) as client:
        heavy = client.app.state.bodies.heavy
        asset = client.app.state.store.load(mesh_id=mesh_id)
        # distinct bodies: the second request cannot wait for the first's
        assert scene_levels_for(asset, ratio=0.4) != scene_levels_for(asset, ratio=1.0)
        first = []
        thread = threading.Thread(target=lambda: first.append(_lod(client, mesh_id, 1.0)))
        thread.start()
        try:
            assert entered.wait(60), "the first scene level never started encoding"
            assert heavy.free == 0
            for response in (_lod(client, mesh_id, 0.4),
                             client.get(f"/meshes/{mesh_id}/chain", params={"lods": "1,0.5"})):
                assert response.status_code == 503, response.text
                assert response.headers["retry-after"] == "1"
                assert "busy" in response.json()["message"]
            part = client.get(f"/meshes/{mesh_id}/parts/0/lod", params={"ratio": 0.5})
            pm = client.app.state.store.load(mesh_id=mesh_id).parts[0].pm
            assert heavy.weight(level_bytes(pm, pm.level_for(ratio=0.5), "json")) == 0
            assert part.status_code == 200
        finally:
            release.set()
            thread.join(60)
        assert [r.status_code for r in first] == [200]
        assert heavy.free == 2
        assert _lod(client, mesh_id, 0.4).status_code == 200


def test_a_scene_level_within_a_default_slot_is_light(scene, monkeypatch):
    """At the default slot size the same scene level is light work: served while
    every slot is held."""
    data, mesh_id = scene
    with _app(data) as client:
        heavy = client.app.state.bodies.heavy
        with heavy.hold(heavy.slots, timeout=0):
            assert _lod(client, mesh_id, 0.7).status_code == 200
