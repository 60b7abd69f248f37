"""A real PostgreSQL for the shared-catalogue tests.

``postgres_server`` (session): the URL of a server, ``LODSERVER_TEST_POSTGRES_URL``
when set (``.ci/services/postgres.sh`` exports it), else a cluster this fixture
starts itself the same way (``initdb`` into a temporary folder, as the
``postgres`` user when run as root, ``pg_ctl`` on a free loopback port) and
stops at the end. Without PostgreSQL the tests using it skip, or fail under
``CI=true`` (``need``).

``postgres_url`` (module): a fresh, empty database on that server, dropped after
the module, so modules never see each other's rows.
"""

from __future__ import annotations

import glob
import os
import secrets
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest

from ..conftest import need

ENV = "LODSERVER_TEST_POSTGRES_URL"


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _binaries() -> Path | None:
    """The newest Debian PostgreSQL bin folder, or None."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"),
                   key=lambda path: int(Path(path).parts[-3]) if Path(path).parts[-3].isdigit()
                   else 0)
    return Path(found[-1]).parent if found else None


def _start_cluster(folder: Path) -> tuple[str, list[str], list[str]]:
    """initdb + pg_ctl start in ``folder``; the URL, the stop command and the start
    command (a test that stops the server starts it again with it)."""
    bin_dir = _binaries()
    if bin_dir is None:
        need("PostgreSQL is not installed (Debian: apt-get install postgresql); "
             f"or set {ENV}")
    as_user = []
    if os.geteuid() == 0:               # initdb refuses root: the postgres user owns it
        shutil.chown(folder, user="postgres")
        as_user = ["runuser", "-u", "postgres", "--"]
    port = _free_port()
    data = folder / "data"
    start = [str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(folder / "server.log"),
             "-w", "-t", "60", "-o", f"-c listen_addresses=127.0.0.1 -p {port} "
             f"-k {folder} -c fsync=off -c max_connections=200", "start"]
    for command in ([str(bin_dir / "initdb"), "-D", str(data), "-U", "postgres", "-A", "trust",
                     "--no-sync"], start):
        done = subprocess.run([*as_user, *command], capture_output=True, text=True)
        if done.returncode:
            # the folder's parents must be searchable by the postgres user (TMPDIR)
            raise RuntimeError(f"{Path(command[0]).name} failed: "
                               f"{(done.stderr or done.stdout).strip()[-500:]}")
    stop = [*as_user, str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop"]
    return f"postgresql://postgres@127.0.0.1:{port}/postgres", stop, [*as_user, *start]


@pytest.fixture(scope="session")
def postgres_server():
    """The URL of a running PostgreSQL server (its ``postgres`` database)."""
    try:
        import psycopg  # noqa: F401
    except ImportError:
        need("psycopg is not installed (pip install -e '.[distributed]')")
    url = os.environ.get(ENV)
    if url:
        yield url
        return
    folder = Path(tempfile.mkdtemp(prefix="lodserver-pg-"))
    stop = None
    try:
        url, stop, _ = _start_cluster(folder)
        yield url
    finally:
        if stop is not None:
            subprocess.run(stop, capture_output=True)
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def postgres_cluster():
    """A PostgreSQL server of the test's own, which it may stop and start again:
    ``(url, stop, start)``, each a callable; stopped at the end. Needs the server
    binaries even when ``LODSERVER_TEST_POSTGRES_URL`` names a shared server."""
    try:
        import psycopg  # noqa: F401
    except ImportError:
        need("psycopg is not installed (pip install -e '.[distributed]')")
    folder = Path(tempfile.mkdtemp(prefix="lodserver-pg-"))
    stop = None
    try:
        url, stop, start = _start_cluster(folder)
        run = (lambda command: subprocess.run(command, capture_output=True, check=True))
        yield url, (lambda: run(stop)), (lambda: run(start))
    finally:
        if stop is not None:
            subprocess.run(stop, capture_output=True)
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="module")
def postgres_url(postgres_server):
    """The URL of a new empty database on ``postgres_server``, dropped afterwards."""
    import psycopg

    name = f"lodserver_test_{secrets.token_hex(6)}"
    with psycopg.connect(postgres_server, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    base, _, _ = postgres_server.rpartition("/")
    yield f"{base}/{name}"
    with psycopg.connect(postgres_server, autocommit=True) as admin:
        # WITH (FORCE): a server process a test killed may still hold a session
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
