"""The object store cut off for a while under load: a real ``lodserver serve`` on
PostgreSQL and moto's S3, reached through a TCP gate that resets every
connection while the store is "down".

Uploads and level requests run in a loop meanwhile. Every answer is a 2xx or a
503 with ``Retry-After`` (never a 500, never a reset connection); once the
store is back every accepted upload ends ready, built once, and the bucket
and the rows match (each object has its row, each ready row its object).

The loop itself is :class:`StoreLoad`, which ``bench/chaos_store.py`` runs
for a full minute's outage and counts."""

from __future__ import annotations

import random
import threading
import time
from collections import Counter

import httpx

from lodserver.service.catalog import open_catalog

from ..meshes import DATA
from ..server import serve, upload
from ..service.test_chaos import (BUILD_TIMEOUT, _check_no_orphans, _env, _keys, _poll,
                                  bucket, gate)  # noqa: F401 (fixtures)
from ..services.postgres import postgres_server, postgres_url  # noqa: F401 (fixtures)
from ..services.s3 import s3_endpoint  # noqa: F401 (a fixture)

SOURCE = DATA / "spot.obj"
# Settings that send reads to the store: one mesh kept loaded and no artefact
# kept on disk beyond the last fetched, so reads alternating over two meshes
# fetch their artefact each time.
READS_FROM_STORE = {"LODSERVER_LOADED_MESHES": "1", "LODSERVER_CACHE_BYTES": "0",
                    "LODSERVER_BODY_CACHE_BYTES": "0"}


class StoreLoad:
    """Uploads (one thread) and level requests over ``readable`` meshes (another),
    in a loop until :meth:`stop`; counts each answer by kind and status
    (``"reset"`` for a connection that failed) and keeps the ids of accepted
    uploads. A 503 without ``Retry-After``, or one whose message names a URL,
    counts as ``"503-bad"``."""

    def __init__(self, base: str, readable: list[str], source=SOURCE):
        self.base, self.readable, self.source = base, readable, source
        self.counts: Counter = Counter()
        self.accepted: list[str] = []
        self.problems: list[str] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._loop, args=(job,), daemon=True)
                         for job in (self._upload, self._read)]

    def start(self) -> StoreLoad:
        for thread in self._threads:
            thread.start()
        return self

    def stop(self) -> Counter:
        self._stop.set()
        for thread in self._threads:
            thread.join()
        return self.counts

    def seen(self, kind: str, status) -> int:
        with self._lock:
            return self.counts[kind, status]

    def _loop(self, job) -> None:
        # a client's patience far beyond the store's bounded calls: a request
        # that hangs shows as a "reset" rather than stalling the loop forever
        with httpx.Client(base_url=self.base, timeout=120) as client:
            while not self._stop.is_set():
                kind, response = job(client)
                self._count(kind, response)
                if response is None or response.status_code == 503:
                    self._stop.wait(0.2)     # as a client honouring Retry-After would

    def _upload(self, client):
        try:
            with open(self.source, "rb") as file:
                response = client.post("/meshes", files={"file": (self.source.name, file)})
        except httpx.TransportError as exc:
            self._problem(f"upload: {type(exc).__name__}")
            return "upload", None
        if response.status_code == 202:
            with self._lock:
                self.accepted.append(response.json()["id"])
        return "upload", response

    def _read(self, client):
        mesh_id = random.choice(self.readable)
        ratio = round(random.uniform(0.05, 1.0), 3)     # rarely a cached body
        try:
            response = client.get(f"/meshes/{mesh_id}/lod",
                                  params={"ratio": ratio, "format": "glb"})
        except httpx.TransportError as exc:
            self._problem(f"level: {type(exc).__name__}")
            return "level", None
        return "level", response

    def _count(self, kind: str, response) -> None:
        if response is None:
            status = "reset"
        else:
            status = response.status_code
            if status == 503 and ("retry-after" not in response.headers
                                  or "://" in response.text or "127.0.0.1" in response.text):
                status = "503-bad"
                self._problem(f"{kind}: 503 {response.headers} {response.text}")
            elif status >= 500 and status != 503:
                self._problem(f"{kind}: {status} {response.text}")
        with self._lock:
            self.counts[kind, status] += 1

    def _problem(self, text: str) -> None:
        with self._lock:
            if len(self.problems) < 20:
                self.problems.append(text)


def run_outage(client: httpx.Client, gate, *, outage: float, readable: list[str]
               ) -> StoreLoad:
    """Run a :class:`StoreLoad` against the server of ``client``; once it has
    answers of both kinds, cut the store off for ``outage`` seconds, then let the
    load go on until both kinds succeed again; the stopped load."""
    load = StoreLoad(str(client.base_url), readable).start()
    try:
        _poll(lambda: (load.seen("upload", 202), load.seen("level", 200)),
              lambda seen: min(seen) >= 2, BUILD_TIMEOUT)
        gate.cut()
        # the outage's length is the scenario, not a bound on anything
        time.sleep(outage)
        gate.restore()
        after = (load.seen("upload", 202), load.seen("level", 200))
        _poll(lambda: (load.seen("upload", 202), load.seen("level", 200)),
              lambda seen: seen[0] >= after[0] + 2 and seen[1] >= after[1] + 2, BUILD_TIMEOUT)
    finally:
        load.stop()
    return load


def upload_readable(client: httpx.Client, count: int = 2) -> list[str]:
    """Upload :data:`SOURCE` ``count`` times (each answer a 202): the ids of the
    meshes the load's level requests read."""
    readable = []
    for _ in range(count):
        with open(SOURCE, "rb") as file:
            readable.append(upload(client, SOURCE.name, file))
    return readable


def wait_all_ready(client: httpx.Client, mesh_ids) -> dict:
    """Poll until every mesh is ready or failed; {id: GET /meshes/{id} body}."""
    bodies = {}
    for mesh_id in mesh_ids:
        bodies[mesh_id] = _poll(lambda: client.get(f"/meshes/{mesh_id}").json(),
                                lambda body: body.get("status") in ("ready", "failed"),
                                BUILD_TIMEOUT, pause=0.2)
    return bodies


def test_a_store_outage_under_load_is_503s_then_every_upload_ready_once(
        postgres_url, bucket, gate, tmp_path, capsys):  # noqa: F811
    s3, name = bucket
    catalog = open_catalog(postgres_url, data_dir=tmp_path)
    catalog._run("DELETE FROM meshes")
    env = _env(postgres_url, f"s3://{name}/prefix", gate.endpoint, **READS_FROM_STORE)
    try:
        with serve(tmp_path / "a", env=env, timeout=120, log=tmp_path / "server.log") as client:
            readable = upload_readable(client)
            assert all(body["status"] == "ready"
                       for body in wait_all_ready(client, readable).values())
            load = run_outage(client, gate, outage=8.0, readable=readable)
            with capsys.disabled():
                print(f"\n[store cut 8 s] {dict(sorted(load.counts.items(), key=str))}")
            statuses = {status for _, status in load.counts}
            assert statuses <= {200, 202, 503}, (dict(load.counts), load.problems)
            # the outage was seen: both kinds were answered 503 while it lasted
            assert load.seen("upload", 503) and load.seen("level", 503), dict(load.counts)
            bodies = wait_all_ready(client, load.accepted)
            failed = {i: b.get("failure") for i, b in bodies.items() if b["status"] != "ready"}
            assert not failed, failed
        accepted = [*readable, *load.accepted]
        rows, _ = catalog._run("SELECT id, status, attempt FROM meshes")
        assert sorted(row[0] for row in rows) == sorted(accepted)   # no row of a 503
        assert all(row[1] == "ready" for row in rows), rows
        # once built and marked done; a build stopped by the outage went back to the queue
        _check_no_orphans(catalog, _keys(s3, name))
    finally:
        catalog.close()
