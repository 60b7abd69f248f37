"""Versioned, CDN-ready URLs: a year for a URL naming the artefact, a minute without."""

from __future__ import annotations

import re
from dataclasses import replace
from types import SimpleNamespace
from urllib.parse import parse_qsl

import pytest
from fastapi import HTTPException

from lodserver.api.caching import (
    IMMUTABLE,
    REVALIDATE,
    VERSION_DIGITS,
    cache_control,
    load_versioned,
    version_of,
    versioned_urls,
)
from lodserver.api.models import MeshPublic
from lodserver.service.store import Status

from ..meshes import textured_spot_glb
from ..services.s3 import s3_endpoint, s3_url  # noqa: F401 (fixtures)
from .test_api import _client, _upload, _wait_ready

PARAMS = {"lod": {"ratio": 0.25}, "splits": {"from": 2000, "to": 2500},
          "chain": {"lods": "1,0.3"}, "materials": {}}


@pytest.fixture(scope="module")
def textured(tmp_path_factory):
    """A client with the textured spot built; (client, mesh JSON)."""
    with _client(tmp_path_factory.mktemp("cdn")) as client:
        created = _upload(client, content=textured_spot_glb(), filename="spot.glb")
        assert created.status_code == 202, created.text
        mesh = _wait_ready(client, created.json()["id"])
        assert mesh["status"] == "ready"
        yield client, mesh


def _get(client, url: str, params: dict, **headers):
    """GET ``url`` (which may hold a query, as the handed-out URLs do) with more
    ``params`` appended (httpx would replace the URL's query by ``params``)."""
    base, _, query = url.partition("?")
    return client.get(base, params={**dict(parse_qsl(query)), **params}, headers=headers)


def test_a_ready_mesh_hands_out_its_version_and_versioned_urls(textured):
    client, mesh = textured
    digest = client.app.state.store.get(mesh_id=mesh["id"]).digest
    assert re.fullmatch(r"[0-9a-f]{64}", digest)
    assert mesh["version"] == digest[:VERSION_DIGITS]
    assert mesh["urls"] == {route: f"/meshes/{mesh['id']}/{route}?v={mesh['version']}"
                            for route in ("lod", "splits", "chain", "materials")}
    listed = {m["id"]: m for m in client.get("/meshes").json()["meshes"]}
    assert listed[mesh["id"]]["urls"] == mesh["urls"]


@pytest.mark.parametrize("status", [Status.QUEUED, Status.BUILDING, Status.FAILED])
def test_a_mesh_not_ready_has_no_version(textured, status):
    client, mesh = textured
    record = client.app.state.store.get(mesh_id=mesh["id"])
    public = MeshPublic.from_record(replace(record, status=status))
    assert public.version is None and public.urls is None


@pytest.mark.parametrize("route", list(PARAMS))
def test_versioned_urls_are_immutable_and_unversioned_ones_revalidate(textured, route):
    client, mesh = textured
    versioned = _get(client, mesh["urls"][route], PARAMS[route])
    plain = _get(client, f"/meshes/{mesh['id']}/{route}", PARAMS[route])
    assert versioned.status_code == plain.status_code == 200, versioned.text
    assert versioned.headers["cache-control"] == IMMUTABLE == "public, max-age=31536000, immutable"
    assert plain.headers["cache-control"] == REVALIDATE
    assert "immutable" not in plain.headers["cache-control"]
    # one artefact, one ETag: a CDN revalidating the plain URL gets a 304 that
    # carries the plain URL's policy, and the versioned URL's 304 its own
    if route in ("splits", "chain"):        # the json forms link as asked (below)
        assert versioned.headers["etag"] == plain.headers["etag"]
    for response in (versioned, plain):
        url = mesh["urls"][route] if response is versioned else f"/meshes/{mesh['id']}/{route}"
        again = _get(client, url, PARAMS[route], **{"If-None-Match": response.headers["etag"]})
        assert again.status_code == 304 and again.content == b""
        assert again.headers["cache-control"] == response.headers["cache-control"]
        assert again.headers["etag"] == response.headers["etag"]
    if route in ("splits", "chain"):
        assert versioned.content == plain.content


def test_a_json_level_links_its_materials_as_it_was_asked_for(textured):
    """Versioned documents link versioned URLs, unversioned ones by id: a client
    following links stays at one version (or always at the latest)."""
    client, mesh = textured
    versioned = _get(client, mesh["urls"]["lod"], {"ratio": 0.5})
    plain = _get(client, f"/meshes/{mesh['id']}/lod", {"ratio": 0.5})
    assert versioned.json()["materials"] == mesh["urls"]["materials"]
    assert plain.json()["materials"] == f"/meshes/{mesh['id']}/materials"
    assert versioned.headers["etag"] != plain.headers["etag"]
    # the other formats name nothing: one body, one ETag
    glb = [_get(client, url, {"ratio": 0.5, "format": "glb"})
           for url in (mesh["urls"]["lod"], f"/meshes/{mesh['id']}/lod")]
    assert glb[0].headers["etag"] == glb[1].headers["etag"]
    assert glb[0].content == glb[1].content


def test_versioned_materials_name_versioned_images(textured):
    client, mesh = textured
    document = _get(client, mesh["urls"]["materials"], {}).json()
    (image,) = document["images"]
    assert image["uri"] == f"images/0?v={mesh['version']}"
    # relative to the materials document, as a glTF client resolves it
    png = _get(client, f"/meshes/{mesh['id']}/{image['uri']}", {})
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.headers["cache-control"] == IMMUTABLE
    assert client.get(f"/meshes/{mesh['id']}/images/0").headers["cache-control"] == REVALIDATE
    assert client.get(f"/meshes/{mesh['id']}/materials").json()["images"][0]["uri"] == "images/0"


@pytest.mark.parametrize("route", [*PARAMS, "images/0"])
def test_a_version_the_mesh_does_not_have_is_a_404_no_cache_keeps(textured, route):
    client, mesh = textured
    other = "0" * VERSION_DIGITS if mesh["version"] != "0" * VERSION_DIGITS else "1" * 16
    response = client.get(f"/meshes/{mesh['id']}/{route}",
                          params={**PARAMS.get(route, {}), "v": other})
    assert response.status_code == 404
    assert response.headers["cache-control"] == "no-store"
    message = response.json()["message"]
    assert f"no version '{other}'" in message and mesh["version"] in message
    assert "/tmp" not in message and "data" not in message


@pytest.mark.parametrize("bad", ["", "abc", "0" * 15, "0" * 17, "G" * 16, "A" * 16, "0" * 64])
def test_a_malformed_version_is_a_422(textured, bad):
    client, mesh = textured
    response = client.get(f"/meshes/{mesh['id']}/lod", params={"ratio": 0.5, "v": bad})
    assert response.status_code == 422 and "'v'" in response.json()["message"]


def test_an_unknown_mesh_with_a_version_is_a_404(textured):
    client, _ = textured
    response = client.get("/meshes/AAAAAAAAAAAAAAAAAAAAAA/lod",
                          params={"ratio": 0.5, "v": "0" * VERSION_DIGITS})
    assert response.status_code == 404 and "no mesh has the id" in response.json()["message"]


# ---- the policy alone ---------------------------------------------------------------

DIGEST_A = "a" * 16 + "0" * 48
DIGEST_B = "b" * 16 + "0" * 48


def test_cache_control_policy():
    assert version_of(DIGEST_A) == "a" * 16 and version_of(None) is None
    assert cache_control(DIGEST_A, "m", None) == REVALIDATE
    assert cache_control(DIGEST_A, "m", "a" * 16) == IMMUTABLE
    with pytest.raises(HTTPException) as caught:
        cache_control(DIGEST_B, "m", "a" * 16)           # rebuilt: the old v is gone
    assert caught.value.status_code == 404 and caught.value.headers == {"Cache-Control": "no-store"}
    assert versioned_urls("m", None) is None
    assert versioned_urls("m", DIGEST_A)["splits"] == f"/meshes/m/splits?v={'a' * 16}"


class FlippingStore:
    """A store whose mesh is rebuilt (its digest changes) while a request loads it."""

    def __init__(self, digests):
        self.digests, self.reads, self.loads = list(digests), 0, 0

    def get(self, *, mesh_id):
        digest = self.digests[min(self.reads, len(self.digests) - 1)]
        self.reads += 1
        return SimpleNamespace(digest=digest)

    def load(self, *, mesh_id):
        self.loads += 1
        return f"pm{self.loads}"


def test_a_rebuild_during_a_load_is_never_labelled_with_the_old_version():
    # before, (load), after: A, B -> read again: B, B -> the pm loaded then, as B
    store = FlippingStore([DIGEST_A, DIGEST_B, DIGEST_B, DIGEST_B])
    pm, digest, policy = load_versioned(store, "m", None)
    assert (pm, digest, policy) == ("pm2", DIGEST_B, REVALIDATE)
    # a client asking for A after that rebuild gets the 404, not B's bytes as A's
    store = FlippingStore([DIGEST_A, DIGEST_B, DIGEST_B, DIGEST_B])
    with pytest.raises(HTTPException) as caught:
        load_versioned(store, "m", version_of(DIGEST_A))
    assert caught.value.status_code == 404
    # a wrong version is refused before anything is loaded
    store = FlippingStore([DIGEST_B])
    with pytest.raises(HTTPException):
        load_versioned(store, "m", version_of(DIGEST_A))
    assert store.loads == 0
    # a mesh that never settles: 503, retry
    store = FlippingStore([DIGEST_A, DIGEST_B] * 4)
    with pytest.raises(HTTPException) as caught:
        load_versioned(store, "m", None)
    assert caught.value.status_code == 503


# ---- several servers behind one CDN -------------------------------------------------

def test_servers_sharing_a_store_answer_a_versioned_url_alike(s3_url, tmp_path):
    """A CDN sends each miss to any server: two servers over one object store and
    one catalogue give the same version, bytes, ETag and Cache-Control."""
    shared = {"store_url": s3_url, "catalog_url": f"sqlite:///{tmp_path / 'catalogue.sqlite3'}"}
    with _client(tmp_path / "a", **shared) as first, _client(tmp_path / "b", **shared) as second:
        created = _upload(first, content=textured_spot_glb(), filename="spot.glb")
        assert created.status_code == 202, created.text
        mesh = _wait_ready(first, created.json()["id"])
        assert second.get(f"/meshes/{mesh['id']}").json()["urls"] == mesh["urls"]
        for route, params in PARAMS.items():
            answers = [_get(client, mesh["urls"][route], params) for client in (first, second)]
            assert [answer.status_code for answer in answers] == [200, 200]
            assert answers[0].content == answers[1].content
            for header in ("etag", "cache-control", "content-type"):
                assert answers[0].headers[header] == answers[1].headers[header], (route, header)
