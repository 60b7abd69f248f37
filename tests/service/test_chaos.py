"""Chaos on a shared deployment of real processes (``lodserver serve``, a
PostgreSQL server of the test's own, moto's S3 behind a TCP gate): the
catalogue stopped in the instant between an artefact's write and the row that
makes it done, and builders whose clocks are 30 s off. Each ends with the
build done exactly once; the first also counts the bucket and the rows
against each other: every object has its row, every done row its object."""

import os
import time
from urllib.parse import urlsplit

import httpx
import pytest

from lodserver.service.catalog import open_catalog

from ..meshes import DATA
from ..server import server_process
from ..services.gate import Gate
from ..services.postgres import postgres_cluster, postgres_server, postgres_url  # noqa: F401
from ..services.s3 import (  # noqa: F401 (s3_endpoint: a fixture)
    _boto_credentials, _remove_bucket, s3_endpoint, s3_environment)

# Generous: the machine is shared and a cold numba cache compiles for a minute.
BUILD_TIMEOUT = 300
# Long enough that a restart of PostgreSQL on a loaded machine fits in it.
LEASE_SECONDS = 30.0
POLL_SECONDS = 0.2


@pytest.fixture
def bucket(s3_endpoint):
    """A fresh bucket on the S3 server (not behind the gate): (boto3 client, name)."""
    import uuid

    import boto3

    client = boto3.client("s3", endpoint_url=s3_endpoint, **_boto_credentials())
    name = f"lodserver-chaos-{uuid.uuid4().hex[:12]}"
    client.create_bucket(Bucket=name)
    try:
        yield client, name
    finally:
        _remove_bucket(client, name)


@pytest.fixture
def gate(s3_endpoint):
    """A :class:`Gate` in front of the S3 server."""
    where = urlsplit(s3_endpoint)
    gate = Gate((where.hostname, where.port))
    try:
        yield gate
    finally:
        gate.close()


def _env(catalog_url, store_url, endpoint, **more):
    return {"LODSERVER_CATALOG_URL": catalog_url, "LODSERVER_STORE_URL": store_url,
            "LODSERVER_LEASE_SECONDS": str(LEASE_SECONDS),
            "LODSERVER_QUEUE_POLL_SECONDS": str(POLL_SECONDS),
            **s3_environment(endpoint), **more}


def _keys(client, name) -> set[str]:
    """Every key of the bucket, without the store's prefix."""
    found = set()
    for page in client.get_paginator("list_objects_v2").paginate(Bucket=name):
        found.update(item["Key"].removeprefix("prefix/") for item in page.get("Contents", []))
    return found


def _check_no_orphans(catalog, keys: set[str]) -> None:
    """Each object has its row (a source: a queued or building row; an artefact: the
    ready row naming its digest) and each ready row has its artefact."""
    rows = {mesh_id: (file_type, status, digest)
            for mesh_id, file_type, status, digest in catalog.artefacts()}
    wanted = set()
    for mesh_id, (file_type, status, digest) in rows.items():
        if status in ("queued", "building"):
            wanted.add(f"sources/{mesh_id}.{file_type}")
        elif status == "ready":
            wanted.add(f"artefacts/{mesh_id}.{digest}.pm")
    assert keys == wanted, (f"objects without a row: {sorted(keys - wanted)}; rows without "
                            f"their object: {sorted(wanted - keys)}")


def _upload(client, path) -> str:
    with open(path, "rb") as file:
        created = client.post("/meshes", files={"file": (path.name, file)})
    assert created.status_code == 202, created.text
    return created.json()["id"]


def _poll(what, until, timeout, pause=0.05):
    """``what()`` once ``until(value)`` holds, polling up to ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = what()
        if until(value):
            return value
        assert time.monotonic() < deadline, f"still {value!r} after {timeout} s"
        time.sleep(pause)


def _status(client, mesh_id):
    try:
        response = client.get(f"/meshes/{mesh_id}")
    except httpx.TransportError:
        return None
    return response.json()["status"] if response.status_code == 200 else response.status_code


def test_postgres_stopped_between_the_artefact_and_its_row(postgres_cluster, bucket, gate,
                                                          tmp_path):
    """The server's PUT of the artefact goes through to S3 but its answer is held
    by the gate: the build is paused after the object exists and before the row
    says done. PostgreSQL is stopped then, the answer released (the builder now
    writes to a catalogue that is down), PostgreSQL started again: the build is
    done once, under its first claim, with exactly its artefact in the bucket."""
    url, stop_postgres, start_postgres = postgres_cluster
    s3, name = bucket
    env = _env(url, f"s3://{name}/prefix", gate.endpoint)
    log = tmp_path / "server.log"
    with server_process(tmp_path / "a", env=env, timeout=120, log=log) as (base, _), \
            httpx.Client(base_url=base, timeout=60) as client:
        gate.hold_answer_to(f"/{name}/prefix/artefacts/".encode())
        mesh_id = _upload(client, DATA / "spot.obj")
        assert gate.seen.wait(BUILD_TIMEOUT), (client.get(f"/meshes/{mesh_id}").json(),
                                               _keys(s3, name))
        # the object is in the bucket (its body may follow the request's head)...
        _poll(lambda: _keys(s3, name), lambda keys: any(k.startswith("artefacts/")
                                                       for k in keys), 60)
        # ...and the row is not done: the builder waits for the store's answer
        assert client.get(f"/meshes/{mesh_id}").json()["status"] == "building"
        stop_postgres()
        gate.release()
        _poll(lambda: log.read_text(errors="replace"),
              lambda text: "cannot be marked ready yet" in text, 60)
        down = client.get(f"/meshes/{mesh_id}")
        assert down.status_code == 503 and "Retry-After" in down.headers, down.text
        start_postgres()
        _poll(lambda: _status(client, mesh_id), lambda status: status in ("ready", "failed"),
              BUILD_TIMEOUT)
        body = client.get(f"/meshes/{mesh_id}").json()
        assert body["status"] == "ready", body
        level = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5, "format": "glb"})
        assert level.status_code == 200 and level.content[:4] == b"glTF"
    catalog = open_catalog(url, data_dir=tmp_path)
    try:
        record = catalog.get(mesh_id=mesh_id)
        assert record.attempt == 1                  # claimed once, done once
        rows, _ = catalog._run("SELECT COUNT(*) FROM meshes")
        assert rows[0][0] == 1
        keys = _keys(s3, name)
        assert keys == {f"artefacts/{mesh_id}.{record.digest}.pm"}
        _check_no_orphans(catalog, keys)
    finally:
        catalog.close()


@pytest.mark.parametrize("skew", [-30.0, 30.0])
def test_leases_run_on_the_databases_clock(postgres_url, skew, tmp_path, capsys):  # noqa: F811
    """A ``lodserver worker`` whose clock is ``skew`` seconds off (time.time shifted
    in the process by a sitecustomize) builds under a lease that the database
    dates: its expiry is at most a lease ahead of PostgreSQL's clock, neither
    ``skew`` past it (held late) nor behind it (stolen at once), and a worker
    with the right clock started beside it does not take the build over."""
    import trimesh

    from ..meshes import _grid
    from .test_shared_servers import _worker

    # a build of many seconds, long enough for a second worker to start beside it
    positions, faces = _grid(900, 900)
    source = tmp_path / "field.ply"
    trimesh.Trimesh(positions, faces, process=False).export(source, encoding="binary")

    shifted = tmp_path / "shifted"
    shifted.mkdir()
    (shifted / "sitecustomize.py").write_text(
        "import time\n"
        f"_time, _time_ns = time.time, time.time_ns\n"
        f"time.time = lambda: _time() + {skew!r}\n"
        f"time.time_ns = lambda: _time_ns() + {int(skew * 1e9)}\n")
    lease = 3.0
    env = {"LODSERVER_CATALOG_URL": postgres_url,
           "LODSERVER_STORE_URL": str(tmp_path / "shared" / "store"),
           "LODSERVER_LEASE_SECONDS": str(lease), "LODSERVER_QUEUE_POLL_SECONDS": "0.2"}
    off_env = {**env, "PYTHONPATH": os.pathsep.join(
        [str(shifted), *filter(None, [os.environ.get("PYTHONPATH")])])}
    catalog = open_catalog(postgres_url, data_dir=tmp_path)
    clock = "SELECT EXTRACT(EPOCH FROM clock_timestamp())::float8"
    try:
        catalog._run("DELETE FROM meshes")
        with server_process(tmp_path / "web", env={**env, "LODSERVER_WORKERS": "0"},
                            timeout=120, log=tmp_path / "web.log") as (base, _), \
                httpx.Client(base_url=base, timeout=60) as client:
            mesh_id = _upload(client, source)
            with _worker(tmp_path / "off", off_env):
                record = _poll(lambda: catalog.get(mesh_id=mesh_id),
                               lambda r: r.status.value != "queued" and r.progress > 0.01
                               or r.status.value == "ready", BUILD_TIMEOUT)
                assert record.status.value == "building", "built before it could be watched"
                now = catalog._run(clock)[0][0][0]
                # the worker's own writes carry its clock: the shift is in effect
                assert abs(record.updated - now - skew) < 10, (record.updated - now, skew)
                ahead = [catalog.lease(mesh_id=mesh_id)[1] - catalog._run(clock)[0][0][0]]
                with _worker(tmp_path / "right", env):
                    _poll(lambda: (tmp_path / "right.log").read_text(errors="replace"),
                          lambda text: "building from the queue" in text, BUILD_TIMEOUT)
                    assert catalog.get(mesh_id=mesh_id).status.value == "building", \
                        "built before the second worker was up"
                    while (record := catalog.get(mesh_id=mesh_id)).status.value == "building":
                        until = catalog.lease(mesh_id=mesh_id)[1]
                        if until is not None:
                            ahead.append(until - catalog._run(clock)[0][0][0])
                        time.sleep(0.1)
            assert record.status.value == "ready", record
            assert record.attempt == 1, "the build was taken over"
            assert 0 < min(ahead) and max(ahead) <= lease + 0.5, (min(ahead), max(ahead))
            with capsys.disabled():
                print(f"\n[clock {skew:+g} s] lease expiry ahead of the database's clock: "
                      f"{min(ahead):.2f}-{max(ahead):.2f} s over {len(ahead)} looks "
                      f"(lease {lease} s); one claim")
    finally:
        catalog.close()


def test_a_worker_killed_and_another_paused_past_its_lease(postgres_url, tmp_path):  # noqa: F811
    """Three ``lodserver worker`` processes: the first to claim the build is killed
    (SIGKILL) mid-build, the one that takes it over is paused (SIGSTOP) past its
    lease, a third takes it over and completes it; the paused one, resumed, is
    fenced and stops. The build is done once (three claims), with one artefact
    in the shared store and no source left."""
    import signal
    import subprocess
    import sys

    from .test_shared_servers import _big_mesh

    lease = 3.0
    store = tmp_path / "shared" / "store"
    env = {**os.environ, "LODSERVER_CATALOG_URL": postgres_url, "LODSERVER_STORE_URL": str(store),
           "LODSERVER_LEASE_SECONDS": str(lease), "LODSERVER_QUEUE_POLL_SECONDS": "0.2",
           "LODSERVER_WARM_KERNELS": "false"}
    workers, logs = {}, {}

    def start(name):
        logs[name] = tmp_path / f"{name}.log"
        with open(logs[name], "wb") as out:
            workers[name] = subprocess.Popen(
                [sys.executable, "-m", "lodserver.cli", "worker", "--data",
                 str(tmp_path / name), "--log-level", "warning"],
                env=env, stdout=out, stderr=subprocess.STDOUT)

    def holder():
        owner = catalog.lease(mesh_id=mesh_id)[0]
        return next((name for name in workers if owner and owner.startswith(nodes.get(name, "?"))),
                    None)

    def building(attempt):
        return _poll(lambda: catalog.get(mesh_id=mesh_id),
                     lambda r: r.status.value == "ready" or (r.attempt == attempt and
                                                             r.progress > 0.01), BUILD_TIMEOUT)

    catalog = open_catalog(postgres_url, data_dir=tmp_path)
    catalog._run("DELETE FROM meshes")
    nodes = {}
    try:
        with server_process(tmp_path / "web", timeout=120, log=tmp_path / "web.log",
                            env={k: v for k, v in env.items() if k.startswith("LODSERVER_")}
                            | {"LODSERVER_WORKERS": "0"}) as (base, _), \
                httpx.Client(base_url=base, timeout=60) as client:
            mesh_id = _upload(client, _big_mesh(tmp_path))
            for name in ("a", "b"):
                start(name)
            for name in ("a", "b"):
                _poll(lambda: (tmp_path / name / "node").exists(), bool, BUILD_TIMEOUT)
                nodes[name] = (tmp_path / name / "node").read_text().strip() + "/"
            record = building(1)
            assert record.status.value == "building", "built before the kill"
            killed = holder()
            workers[killed].send_signal(signal.SIGKILL)
            workers[killed].wait()
            record = building(2)
            assert record.status.value == "building", "built before the pause"
            paused = holder()
            assert paused not in (None, killed)
            workers[paused].send_signal(signal.SIGSTOP)
            start("c")
            _poll(lambda: (tmp_path / "c" / "node").exists(), bool, BUILD_TIMEOUT)
            nodes["c"] = (tmp_path / "c" / "node").read_text().strip() + "/"
            record = _poll(lambda: catalog.get(mesh_id=mesh_id),
                           lambda r: r.status.value in ("ready", "failed"), BUILD_TIMEOUT)
            assert record.status.value == "ready", record
            assert record.attempt == 3, record.attempt
            workers[paused].send_signal(signal.SIGCONT)
            # resumed mid-build, it learns it lost the lease at its next heartbeat
            # or progress write, at the latest when its fenced commit is refused
            assert _noticed(logs[paused], BUILD_TIMEOUT), logs[paused].read_text()
            workers["c"].send_signal(signal.SIGTERM)
            assert workers["c"].wait(timeout=60) == 0, logs["c"].read_text()
            workers[paused].send_signal(signal.SIGTERM)
            assert workers[paused].wait(timeout=60) == 0, logs[paused].read_text()
            final = catalog.get(mesh_id=mesh_id)
            assert (final.status.value, final.attempt, final.digest) == \
                ("ready", 3, record.digest)
            level = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.1, "format": "glb"})
            assert level.status_code == 200 and level.content[:4] == b"glTF"
        assert catalog._run("SELECT COUNT(*) FROM meshes")[0][0][0] == 1
        assert [p.name for p in (store / "artefacts").iterdir()] == \
            [f"{mesh_id}.{record.digest}.pm"]
        assert list((store / "sources").iterdir()) == []
    finally:
        for process in workers.values():
            if process.poll() is None:
                process.send_signal(signal.SIGCONT)
                process.kill()
                process.wait()
        catalog.close()


def _noticed(log, timeout: float) -> bool:
    """Whether the worker writing ``log`` says, within ``timeout`` seconds, that its
    build is no longer its own."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        text = log.read_text(errors="replace")
        if "lost its lease" in text or "no longer held" in text:
            return True
        time.sleep(0.5)
    return False
