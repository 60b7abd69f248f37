"""The viewer's files: versioned URLs, gzip, ETags, Cache-Control, and the CSP
following the page as served (lodserver/api/routes/viewer_files.py)."""

import base64
import gzip
import hashlib
import re

import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.routes.viewer_files import IMMUTABLE, rewrite_page
from lodserver.api.settings import Settings


def _client(tmp_path, static=None):
    options = {"static_dir": static} if static is not None else {}
    return TestClient(create_app(Settings(data_dir=tmp_path / "data", warm_kernels=False,
                                          **options)))


def _version(page: str) -> str:
    return re.search(r'src="\./v/([0-9a-f]+)/main\.js"', page).group(1)


def _importmap_source(html: str) -> str:
    text = re.search(r'<script type="importmap">(.*?)</script>', html, re.S).group(1)
    digest = hashlib.sha256(text.replace("\r\n", "\n").encode()).digest()
    return f"'sha256-{base64.b64encode(digest).decode()}'"


@pytest.fixture
def small_static(tmp_path):
    static = tmp_path / "static"
    (static / "vendor").mkdir(parents=True)
    (static / "index.html").write_text(
        '<!doctype html><script type="importmap">{"imports": {"three": "./vendor/three.js"}}'
        '</script><link rel="stylesheet" href="./viewer.css">'
        '<script type="module" src="./main.js"></script>')
    (static / "main.js").write_text("import * as THREE from 'three';\n" + "// pad\n" * 400)
    (static / "viewer.css").write_text("body { margin: 0 }\n")
    (static / "vendor" / "three.js").write_text("export const REVISION = '1';\n" * 200)
    (static / ".secret").write_text("not served")
    return static


def test_the_page_points_into_its_version_and_is_revalidated(tmp_path):
    with _client(tmp_path) as client:
        page = client.get("/viewer/")
        assert page.status_code == 200
        assert page.headers["cache-control"] == "no-cache"
        version = _version(page.text)
        # every relative URL of the page, the import map's included, is versioned
        assert f'"three": "./v/{version}/vendor/three/build/three.module.js"' in page.text
        assert f'href="./v/{version}/viewer.css"' in page.text
        assert not re.search(r"""["']\./(?!v/)""", page.text)
        # the CSP names the import map of the page as served
        assert _importmap_source(page.text) in page.headers["content-security-policy"]
        again = client.get("/viewer/", headers={"If-None-Match": page.headers["etag"]})
        assert again.status_code == 304 and again.content == b""
        assert client.get("/viewer/index.html").text == page.text


def test_versioned_files_are_immutable_and_gzipped(tmp_path):
    with _client(tmp_path) as client:
        version = _version(client.get("/viewer/").text)
        url = f"/viewer/v/{version}/vendor/three/build/three.core.js"
        packed = client.get(url, headers={"Accept-Encoding": "gzip"})
        assert packed.status_code == 200
        assert packed.headers["cache-control"] == IMMUTABLE
        assert packed.headers["content-encoding"] == "gzip"
        assert packed.headers["vary"] == "Accept-Encoding"
        assert packed.headers["content-type"].startswith("text/javascript")
        wire = int(packed.headers["content-length"])
        plain = client.get(url, headers={"Accept-Encoding": "identity"})
        assert "content-encoding" not in plain.headers
        assert plain.content == packed.content        # httpx inflated the gzip body
        assert wire < len(plain.content) / 3           # three.js gzips about 5:1
        assert plain.headers["etag"] != packed.headers["etag"]
        for response in (packed, plain):
            etag = response.headers["etag"]
            encoding = response.request.headers["accept-encoding"]
            fresh = client.get(url, headers={"If-None-Match": etag, "Accept-Encoding": encoding})
            assert fresh.status_code == 304 and fresh.headers["etag"] == etag
        # q=0 refuses gzip
        refused = client.get(url, headers={"Accept-Encoding": "gzip;q=0, identity"})
        assert "content-encoding" not in refused.headers


def test_a_page_of_gzipped_files_weighs_a_fraction_of_the_files(tmp_path):
    """The JavaScript a cold page load fetches, compressed: under a third of its size."""
    with _client(tmp_path) as client:
        page = client.get("/viewer/")
        version = _version(page.text)
        names = ["vendor/three/build/three.module.js", "vendor/three/build/three.core.js",
                 "main.js", "stream.js", "scene.js"]
        wire = raw = 0
        for name in names:
            response = client.get(f"/viewer/v/{version}/{name}")
            assert response.status_code == 200, name
            wire += int(response.headers["content-length"])
            raw += len(response.content)
        assert wire < raw / 3, (wire, raw)


def test_plain_paths_still_work_and_revalidate(tmp_path):
    with _client(tmp_path) as client:
        response = client.get("/viewer/vsplit.js")
        assert response.status_code == 200 and response.headers["cache-control"] == "no-cache"
        assert "javascript" in response.headers["content-type"]
        assert client.head("/viewer/vsplit.js").status_code == 200


def test_unknown_files_and_versions_are_404_naming_no_path(tmp_path, small_static):
    with _client(tmp_path, small_static) as client:
        version = _version(client.get("/viewer/").text)
        for url in (f"/viewer/v/{version}/nope.js", "/viewer/nope.js", "/viewer/.secret",
                    f"/viewer/v/{version}/.secret", "/viewer/v/0123456789abcdef/main.js",
                    "/viewer/%2e%2e/%2e%2e/etc/passwd", f"/viewer/v/{version}/..%2fmain.js"):
            response = client.get(url)
            assert response.status_code == 404, url
            message = response.json()["message"]
            assert str(small_static) not in message and "/" not in message.rstrip("."), url


def test_an_edit_makes_a_new_version_and_the_old_one_stays_served(tmp_path, small_static):
    with _client(tmp_path, small_static) as client:
        first = client.get("/viewer/")
        old = _version(first.text)
        assert client.get(f"/viewer/v/{old}/main.js").status_code == 200
        (small_static / "main.js").write_text("export const edited = true;\n" * 100)
        second = client.get("/viewer/")
        new = _version(second.text)
        assert new != old and second.headers["etag"] != first.headers["etag"]
        assert "edited" in client.get(f"/viewer/v/{new}/main.js").text
        assert "edited" not in client.get(f"/viewer/v/{old}/main.js").text   # a page mid-load
        # the import map moved into the new version: the CSP follows it
        assert _importmap_source(second.text) in second.headers["content-security-policy"]
        assert _importmap_source(first.text) not in second.headers["content-security-policy"]


def test_gzip_bodies_are_the_same_bytes_on_every_start(tmp_path, small_static):
    """gzip written with mtime 0: a restarted server hands out the same bytes and ETags."""
    etags = []
    for _ in range(2):
        with _client(tmp_path, small_static) as client:
            version = _version(client.get("/viewer/").text)
            response = client.get(f"/viewer/v/{version}/main.js")
            etags.append((version, response.headers["etag"]))
    assert etags[0] == etags[1]


def test_rewrite_page_moves_only_relative_quoted_urls():
    html = ('<a href="./x.css"></a><img src=\'./y.png\'>{"a": "./z.js"} '
            '<link href="data:,"> <a href="https://e.org/./q">')
    out = rewrite_page(html, "abc")
    assert out == ('<a href="./v/abc/x.css"></a><img src=\'./v/abc/y.png\'>{"a": "./v/abc/z.js"} '
                   '<link href="data:,"> <a href="https://e.org/./q">')
    assert gzip.decompress(gzip.compress(out.encode())) == out.encode()
