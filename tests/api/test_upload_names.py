"""Names a client gives (a file's name, the ``name`` field) through the real app,
on a SQLite and a PostgreSQL catalogue: one rule (``io.fileset.check_name``)
for both, so a name with a control character or over 255 UTF-8 bytes is a 422
everywhere, and every name accepted is stored and read back as it was sent."""

import re

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings, strategies as st

from lodserver.api.main import create_app
from lodserver.api.settings import Settings
from lodserver.io.fileset import MAX_NAME_BYTES

from ..services.postgres import postgres_server, postgres_url  # noqa: F401 (fixtures)

TRIANGLE = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
BOUNDARY = "names-test-boundary"
CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")
# one example of each kind of control character, and a few ordinary names
CONTROLS = ["\x00", "\x01", "\t", "\n", "\x1b", "\x1f", "\x7f", "\x80", "\x85", "\x9f"]
PLAIN = ["spot", "a b", "naïve 模型 🐄", "quote'\"s", "‮evil", "x" * MAX_NAME_BYTES,
         "é" * (MAX_NAME_BYTES // 2)]


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def client(request, tmp_path_factory):
    """The app on a catalogue of the kind ``request.param`` names; builds nothing
    (workers=0), so every upload is only checked and stored."""
    catalog_url = None if request.param == "sqlite" else request.getfixturevalue("postgres_url")
    data = tmp_path_factory.mktemp(f"names-{request.param}") / "data"
    app = create_app(Settings(data_dir=data, warm_kernels=False, workers=0,
                              catalog_url=catalog_url))
    with TestClient(app) as client:
        yield client


def _raw_upload(client, filename: str, name: str | None = None):
    """POST a one-triangle OBJ under ``filename``, written raw (UTF-8) into the part's
    header as a client other than a browser may, not percent-escaped as httpx does."""
    body = (f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"file\"; "
            f"filename=\"").encode() + filename.encode("utf-8") + b"\"\r\n\r\n" + TRIANGLE
    if name is not None:
        body += (f"\r\n--{BOUNDARY}\r\nContent-Disposition: form-data; "
                 "name=\"name\"\r\n\r\n").encode() + name.encode("utf-8")
    body += f"\r\n--{BOUNDARY}--\r\n".encode()
    return client.post("/meshes", content=body,
                       headers={"Content-Type": f"multipart/form-data; boundary={BOUNDARY}"})


def _expect(client, answer, name: str) -> None:
    """``answer`` refused ``name`` (422, one sentence) exactly when the rule says so,
    and otherwise stored it as it is."""
    bad = CONTROL.search(name) or len(name.encode("utf-8")) > MAX_NAME_BYTES
    if bad:
        assert answer.status_code == 422, (name, answer.text)
        message = answer.json()["message"]
        assert "control character" in message or "bytes long" in message, message
        return
    assert answer.status_code == 202, (name, answer.text)
    stored = client.get(f"/meshes/{answer.json()['id']}").json()
    assert stored["name"] == name
    listed = {mesh["id"]: mesh["name"] for mesh in client.get("/meshes?limit=1000").json()
              ["meshes"]}
    assert listed[answer.json()["id"]] == name


@pytest.mark.parametrize("name", [f"a{c}b" for c in CONTROLS] + PLAIN
                         + ["x" * (MAX_NAME_BYTES + 1), "é" * (MAX_NAME_BYTES // 2 + 1)])
def test_the_name_field_is_refused_or_kept_as_sent(client, name):
    answer = client.post("/meshes", files={"file": ("tri.obj", TRIANGLE)}, data={"name": name})
    _expect(client, answer, name)


@pytest.mark.parametrize("stem", [f"a{c}b" for c in CONTROLS if c not in "\n"]
                         + [stem for stem in PLAIN if '"' not in stem]
                         + ["x" * (MAX_NAME_BYTES - 3), "x" * (MAX_NAME_BYTES - 3) + "y"])
def test_file_names_are_refused_or_kept_as_sent(client, stem):
    # (a raw newline cannot be sent in a header line at all)
    _expect(client, _raw_upload(client, f"{stem}.obj"), f"{stem}.obj")


def test_a_control_character_in_a_file_of_a_set_is_422(client):
    answer = client.post("/meshes", files=[("file", ("tri.obj", TRIANGLE)),
                                           ("file", ("a\x85.mtl", b"newmtl a\n"))])
    assert answer.status_code == 422, answer.text


_EXAMPLES = settings(max_examples=40, deadline=None,
                     suppress_health_check=[HealthCheck.function_scoped_fixture,
                                            HealthCheck.too_slow])


@_EXAMPLES
@given(name=st.text(min_size=1, max_size=140))
def test_any_name_field_is_refused_exactly_by_the_rule(client, name):
    answer = client.post("/meshes", files={"file": ("tri.obj", TRIANGLE)}, data={"name": name})
    _expect(client, answer, name)


@_EXAMPLES
@given(stem=st.text(st.characters(exclude_characters='"\\/\r\n'), min_size=1, max_size=140)
       .filter(lambda stem: not stem.startswith(".")))
def test_any_file_name_is_refused_exactly_by_the_rule(client, stem):
    _expect(client, _raw_upload(client, f"{stem}.obj"), f"{stem}.obj")
