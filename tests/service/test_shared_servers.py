"""Real ``lodserver serve`` (and ``lodserver worker``) processes sharing one
catalogue (SQLite file | PostgreSQL) and one store (a shared local folder),
each with a data directory of its own: an upload to one is listed, built and
served byte for byte by the other; a delete on one is seen by the other, even
for a mesh it holds in memory; a server killed (SIGKILL) while building has
its build taken over by the other within the lease, and completed once; a
worker builds what a server that only serves accepts."""

import os
import signal
import subprocess
import sys
import time
from contextlib import ExitStack, contextmanager

import httpx
import pytest
import trimesh

from lodserver.service.catalog import open_catalog

from ..meshes import DATA, _grid
from ..server import server_process
from .conftest import DIALECTS

LEASE_SECONDS = 3.0
POLL_SECONDS = 0.2
# Generous: the machine is shared and a cold numba cache compiles for a minute.
BUILD_TIMEOUT = 300


def _env(catalog_url, tmp_path, **more):
    return {"LODSERVER_CATALOG_URL": catalog_url,
            "LODSERVER_STORE_URL": str(tmp_path / "shared" / "store"),
            "LODSERVER_LEASE_SECONDS": str(LEASE_SECONDS),
            "LODSERVER_QUEUE_POLL_SECONDS": str(POLL_SECONDS), **more}


@contextmanager
def _servers(catalog_url, tmp_path, *names, **more):
    """One ``lodserver serve`` per name, data directory tmp_path/<name>; yields
    {name: (httpx client, process)}."""
    with ExitStack() as stack:
        found = {}
        for name in names:
            base, process = stack.enter_context(server_process(
                tmp_path / name, env=_env(catalog_url, tmp_path, **more), timeout=120,
                log=tmp_path / f"{name}.log"))
            client = stack.enter_context(httpx.Client(base_url=base, timeout=120))
            found[name] = (client, process)
        yield found


def _upload(client, path) -> str:
    with open(path, "rb") as file:
        created = client.post("/meshes", files={"file": (path.name, file)})
    assert created.status_code == 202, created.text
    return created.json()["id"]


def _wait(client, mesh_id, until=("ready", "failed"), timeout=BUILD_TIMEOUT, progress=0.0):
    deadline = time.monotonic() + timeout
    while True:
        body = client.get(f"/meshes/{mesh_id}").json()
        if body["status"] in until and body["progress"] >= progress:
            return body
        assert body["status"] != "failed", body["failure"]
        assert time.monotonic() < deadline, f"still {body['status']} after {timeout} s"
        time.sleep(0.05)


def _node(data_dir) -> str:
    return (data_dir / "node").read_text().strip()


def _big_mesh(tmp_path):
    """A height field of 720k faces, saved as binary PLY: a build of seconds even on a
    quiet machine, so the test sees it under way (progress written) and kills it then."""
    positions, faces = _grid(600, 600)
    path = tmp_path / "field.ply"
    trimesh.Trimesh(positions, faces, process=False).export(path, encoding="binary")
    return path


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_two_servers_serve_the_same_meshes_and_see_each_others_deletes(catalog_url, tmp_path):
    with _servers(catalog_url, tmp_path, "a", "b") as servers:
        (a, _), (b, _) = servers["a"], servers["b"]
        mesh_id = _upload(a, DATA / "spot.obj")
        assert [m["id"] for m in b.get("/meshes").json()["meshes"]] == [mesh_id]
        built = _wait(b, mesh_id)
        assert built["status"] == "ready", built
        levels = {}
        for name, client in (("a", a), ("b", b)):
            for params in ({"ratio": 0.25, "format": "glb"}, {"vertices": 300},
                           {"faces": 1000, "format": "ply"}):
                response = client.get(f"/meshes/{mesh_id}/lod", params=params)
                assert response.status_code == 200, response.text
                levels.setdefault(str(params), []).append(response.content)
            packet = client.get(f"/meshes/{mesh_id}/splits", params={"from": 50, "to": 900})
            assert packet.status_code == 200
            levels.setdefault("packet", []).append(packet.content)
        for key, (from_a, from_b) in levels.items():
            assert from_a == from_b, key
        # one artefact in the shared store, the source gone once built
        store = tmp_path / "shared" / "store"
        assert len(list((store / "artefacts").glob(f"{mesh_id}.*.pm"))) == 1
        assert list((store / "sources").iterdir()) == []

        # both hold the mesh in memory now; a delete on b is seen by a at once
        assert b.delete(f"/meshes/{mesh_id}").status_code == 204
        for client in (a, b):
            assert client.get(f"/meshes/{mesh_id}").status_code == 404
            assert client.get(f"/meshes/{mesh_id}/lod",
                              params={"ratio": 0.25}).status_code == 404
            assert client.get("/meshes").json()["meshes"] == []
        assert list((store / "artefacts").iterdir()) == []


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_a_build_whose_server_is_killed_is_taken_over_within_the_lease(catalog_url, tmp_path,
                                                                      capsys):
    source = _big_mesh(tmp_path)
    catalog = open_catalog(catalog_url, data_dir=tmp_path)
    try:
        with _servers(catalog_url, tmp_path, "a", "b") as servers:
            nodes = {_node(tmp_path / name): name for name in servers}
            mesh_id = _upload(servers["a"][0], source)
            # in the kernel (progress written), under whichever server claimed it
            body = _wait(servers["b"][0], mesh_id, until=("building", "ready"), progress=0.01)
            assert body["status"] == "building", "the build ended before it could be killed"
            owner, _ = catalog.lease(mesh_id=mesh_id)
            holder = nodes[owner.split("/")[0]]
            survivor = "b" if holder == "a" else "a"
            servers[holder][1].send_signal(signal.SIGKILL)
            servers[holder][1].wait()
            killed = time.monotonic()
            while (owner := catalog.lease(mesh_id=mesh_id)[0]) is None or \
                    nodes[owner.split("/")[0]] == holder:
                assert time.monotonic() - killed < LEASE_SECONDS + 30, "never taken over"
                time.sleep(0.02)
            taken = time.monotonic() - killed
            client = servers[survivor][0]
            body = _wait(client, mesh_id)
            done = time.monotonic() - killed
            assert body["status"] == "ready", body
            record = catalog.get(mesh_id=mesh_id)
            assert record.attempt == 2            # claimed twice, completed once
            # the lease ran out (at most LEASE_SECONDS after its last renewal), then
            # the survivor's next look at the queue took it
            assert taken <= LEASE_SECONDS + POLL_SECONDS + 5, taken
            level = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.1, "format": "glb"})
            assert level.status_code == 200 and level.content[:4] == b"glTF"
            artefacts = list((tmp_path / "shared" / "store" / "artefacts").iterdir())
            assert [p.name for p in artefacts] == [f"{mesh_id}.{record.digest}.pm"]
            with capsys.disabled():
                print(f"\n[{catalog_url.split(':')[0]}] killed the builder; taken over after "
                      f"{taken:.2f} s (lease {LEASE_SECONDS} s), ready {done:.1f} s after the "
                      "kill")
    finally:
        catalog.close()


@contextmanager
def _worker(data_dir, env):
    """A ``lodserver worker`` process, stopped with SIGTERM (its exit code checked)."""
    command = [sys.executable, "-m", "lodserver.cli", "worker", "--data", str(data_dir),
               "--log-level", "warning"]
    log = open(data_dir.parent / f"{data_dir.name}.log", "wb")
    process = subprocess.Popen(command, env={**os.environ, "LODSERVER_WARM_KERNELS": "false",
                                             **env}, stdout=log, stderr=subprocess.STDOUT)
    try:
        yield process
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=60) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        log.close()


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_a_worker_builds_what_a_serving_only_server_accepts(catalog_url, tmp_path):
    with _servers(catalog_url, tmp_path, "web", LODSERVER_WORKERS="0") as servers:
        web, _ = servers["web"]
        mesh_id = _upload(web, DATA / "spot.obj")
        time.sleep(2 * POLL_SECONDS)
        assert web.get(f"/meshes/{mesh_id}").json()["status"] == "queued"   # nobody builds
        with _worker(tmp_path / "worker", _env(catalog_url, tmp_path)):
            body = _wait(web, mesh_id)
            assert body["status"] == "ready", body
            assert body["vertices"] > body["base_vertices"]
        # the worker stopped; the server serves what it built
        level = web.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5, "format": "glb"})
        assert level.status_code == 200 and level.content[:4] == b"glTF"
