"""``/readyz``: 503 with one sentence while the catalogue or the store cannot be
used, 200 again once they are back; ``/healthz`` stays 200 meanwhile.

The outages are real: a server on PostgreSQL and S3 (moto) reaches both through
TCP proxies the test closes (refused connections) and stalls (nothing
answers), and a server on a local folder store loses its folder. The probe's
reuse of its answer and its deadline are checked on ``Readiness`` itself with
probes that count their calls and block."""

import asyncio
import threading
import time
from urllib.parse import urlsplit

import httpx
import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.routes.health import FRESH_SECONDS, PROBE_SECONDS, Readiness
from lodserver.api.settings import Settings
from lodserver.service.catalog import ANSWER_SECONDS

from ..server import server_process
from ..services.postgres import postgres_server, postgres_url  # noqa: F401 (fixtures)
from ..services.proxy import TcpProxy
from ..services.s3 import s3_endpoint, s3_url  # noqa: F401 (fixtures)

# How long an outage or a recovery may take to show: a cached answer's age, one
# probe's deadline, and slack for a loaded machine.
SHOWS_WITHIN = FRESH_SECONDS + PROBE_SECONDS + 20


def _until(client, status: int, timeout: float = SHOWS_WITHIN) -> httpx.Response:
    """GET /readyz until it answers ``status``; that response."""
    deadline = time.monotonic() + timeout
    while True:
        response = client.get("/readyz")
        if response.status_code == status:
            return response
        assert time.monotonic() < deadline, (f"/readyz still {response.status_code} "
                                             f"{response.text} after {timeout} s")
        time.sleep(0.2)


def _not_ready(response, names: str) -> str:
    body = response.json()
    assert body["status"] == "unavailable" and body["ready"] is False, body
    assert body["message"].startswith(f"the {names} "), body
    assert response.headers["cache-control"] == "no-store"
    return body["message"]


# ---- Readiness itself ------------------------------------------------------------

def test_one_probe_per_period_however_many_ask():
    calls = []

    async def scenario():
        readiness = Readiness({"catalogue": lambda timeout: calls.append(timeout)},
                              fresh=0.5)
        answers = await asyncio.gather(*(readiness.problem() for _ in range(50)))
        assert answers == [None] * 50
        assert calls == [2 * PROBE_SECONDS]     # its own timeouts: twice the deadline
        await asyncio.sleep(0.6)
        assert await readiness.problem() is None
        assert len(calls) == 2

    asyncio.run(scenario())


def test_a_hanging_probe_is_a_503_within_its_deadline_and_never_runs_twice():
    release, calls = threading.Event(), []

    def hangs(timeout):
        calls.append(timeout)
        release.wait(30)

    def fails(timeout):
        raise ConnectionError("postgresql://user:pw@db.internal:5432/x refused")

    async def scenario():
        readiness = Readiness({"catalogue": hangs, "store": fails}, deadline=0.5, fresh=0)
        try:
            for _ in range(3):
                started = time.monotonic()
                assert await readiness.problem() == "the catalogue did not answer within 0.5 s"
                assert time.monotonic() - started < 5
            assert len(calls) == 1          # the hanging probe is waited for, not restarted
            release.set()
            # the catalogue answers now: the store's failure shows, without its details
            deadline = time.monotonic() + 10
            while (problem := await readiness.problem()).startswith("the catalogue"):
                assert time.monotonic() < deadline
            assert problem == "the store cannot be used right now"
        finally:
            release.set()

    asyncio.run(scenario())


# ---- a local folder store ---------------------------------------------------------

def test_a_missing_store_folder_is_503_until_it_is_back(tmp_path):
    store = tmp_path / "store"
    settings = Settings(data_dir=tmp_path / "data", store_url=str(store), warm_kernels=False)
    with TestClient(create_app(settings)) as client:
        assert client.get("/readyz").json() == {"status": "ok", "ready": True}
        for child in store.iterdir():
            child.rmdir()
        store.rmdir()
        message = _not_ready(_until(client, 503), "store")
        assert str(tmp_path) not in message
        assert client.get("/healthz").status_code == 200
        store.mkdir()
        assert _until(client, 200).json() == {"status": "ok", "ready": True}


# ---- PostgreSQL and S3, through proxies -----------------------------------------

def _through(proxy: TcpProxy, url: str) -> str:
    """``url`` with its host and port replaced by the proxy's."""
    parts = urlsplit(url)
    credentials = parts.netloc.rpartition("@")[0]
    netloc = f"{credentials}@{proxy.address}" if credentials else proxy.address
    return parts._replace(netloc=netloc).geturl()


@pytest.fixture
def shared_server(request, tmp_path, postgres_url, s3_url, s3_endpoint):  # noqa: F811
    """A real server whose catalogue (PostgreSQL) and store (S3) are reached through
    proxies, with more settings from an indirect parameter; yields (httpx client,
    catalogue proxy, store proxy, server process)."""
    database, objects = urlsplit(postgres_url), urlsplit(s3_endpoint)
    with TcpProxy((database.hostname, database.port)) as catalogue, \
            TcpProxy((objects.hostname, objects.port)) as store:
        env = {"LODSERVER_CATALOG_URL": _through(catalogue, postgres_url),
               "LODSERVER_STORE_URL": s3_url,
               "AWS_ENDPOINT_URL": _through(store, s3_endpoint),
               **getattr(request, "param", {})}
        with server_process(tmp_path / "data", env=env, timeout=120,
                            log=tmp_path / "server.log") as (base, process), \
                httpx.Client(base_url=base, timeout=60) as client:
            yield client, catalogue, store, process


def test_readyz_follows_postgresql_and_s3_going_away_and_coming_back(shared_server):
    client, catalogue, store, _ = shared_server
    assert client.get("/readyz").json() == {"status": "ok", "ready": True}
    assert client.get("/meshes").status_code == 200

    catalogue.refuse()
    message = _not_ready(_until(client, 503), "catalogue")
    assert message == "the catalogue cannot be used right now"
    assert client.get("/meshes").status_code == 503       # what a balancer now avoids
    assert client.get("/healthz").status_code == 200      # alive: no reason to restart it
    catalogue.restore()
    _until(client, 200)
    assert client.get("/meshes").status_code == 200

    # a database that stops answering: the probe's deadline, not the connection's
    catalogue.hang()
    try:
        response = _until(client, 503)
        assert _not_ready(response, "catalogue") == (
            f"the catalogue did not answer within {PROBE_SECONDS:g} s")
        started = time.monotonic()
        again = client.get("/readyz")
        assert again.status_code == 503 and time.monotonic() - started < PROBE_SECONDS + 5
        assert client.get("/healthz", timeout=10).status_code == 200   # the loop is free
    finally:
        catalogue.restore()
    _until(client, 200)

    store.refuse()
    assert _not_ready(_until(client, 503), "store") == "the store cannot be used right now"
    store.restore()
    _until(client, 200)

    store.hang()
    try:
        assert _not_ready(_until(client, 503), "store") == (
            f"the store did not answer within {PROBE_SECONDS:g} s")
    finally:
        store.restore()
    _until(client, 200)


# A node that builds too: its queue poll waits on the same unanswering
# database, until the catalogue's own deadline on an answer (ANSWER_SECONDS).
@pytest.mark.parametrize("shared_server", [{"LODSERVER_WORKERS": "0"},
                                           {"LODSERVER_WORKERS": "1",
                                            "LODSERVER_QUEUE_POLL_SECONDS": "0.2"}],
                         indirect=True, ids=["serving", "building"])
def test_a_probe_stuck_on_an_unanswering_database_does_not_hold_up_the_shutdown(
        shared_server):
    client, catalogue, _, process = shared_server
    catalogue.hang()
    try:
        _not_ready(_until(client, 503), "catalogue")
        started = time.monotonic()
        process.terminate()
        process.wait(timeout=ANSWER_SECONDS + 120)
        # the probe's thread is a daemon, and closing the catalogue does not wait
        # for it; a queue poll ends once the catalogue gives up on its answer
        # (twice: a pooled connection is tried again once on a new one)
        assert time.monotonic() - started < 2 * ANSWER_SECONDS + 60
    finally:
        catalogue.restore()
