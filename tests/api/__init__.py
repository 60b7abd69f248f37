"""Tests of the HTTP API; :func:`settled` is the wait for a build they share."""

import time


def settled(client, mesh_id: str, timeout: float = 120) -> dict:
    """``GET /meshes/{id}`` once the mesh is ready or failed (a build through
    ``client``, a TestClient), failing the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while (body := client.get(f"/meshes/{mesh_id}").json())["status"] not in ("ready", "failed"):
        assert time.monotonic() < deadline, f"mesh {mesh_id} not settled in {timeout} s"
        time.sleep(0.05)
    return body


def uploaded(client, filename: str, content: bytes, **fields) -> str:
    """The id of ``content`` uploaded as ``filename`` (form ``fields`` beside it)
    through ``client`` and built, failing the test when it is refused or fails."""
    created = client.post("/meshes", files={"file": (filename, content)}, data=fields)
    assert created.status_code == 202, created.text
    mesh_id = created.json()["id"]
    assert settled(client, mesh_id)["status"] == "ready"
    return mesh_id
