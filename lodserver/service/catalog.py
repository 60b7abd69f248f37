"""The catalogue: one row per mesh, which is also the build queue (SQLite | PostgreSQL).

Every server and ``lodserver worker`` given the same ``LODSERVER_CATALOG_URL``
shares one table ``meshes``. Besides what a client sees (status, progress,
counts, failure reason, the artefact's digest) a row holds its queue state:

- ``attempt``     : the fencing token, incremented by every claim. A build's
  writes (progress, failure, the artefact, giving it back) only count with
  ``WHERE attempt = <its claim's>`` and status ``building``, so a build whose
  lease was taken over can never record anything, let alone a second completion;
- ``lease_owner`` : who builds it (``<node>/<incarnation>``, :func:`new_owner`);
- ``lease_until`` : seconds since the epoch, on the database's clock (no
  clock-skew between hosts), until which nobody else may claim it; renewed by
  the builder's heartbeat;
- ``lost``        : how many times its builder vanished (lease expired, or its
  node restarted): a mesh that kills every server building it is failed after
  :data:`MAX_LOST` rather than passed around forever.

A claim is one statement, ``UPDATE ... WHERE id = (SELECT ... LIMIT 1 [FOR
UPDATE SKIP LOCKED]) AND <still claimable> RETURNING ...``: queued rows, and
building rows whose lease expired, oldest first. PostgreSQL's ``SKIP LOCKED``
lets concurrent claimers pass over each other's rows; SQLite runs each write
statement under its single writer lock, so the same statement is atomic there.

The SQL is shared; :data:`DIALECTS` holds the few places the two differ. The
schema is created on first use, under a lock (PostgreSQL advisory lock, SQLite
``BEGIN IMMEDIATE``) so that two servers starting at once do not race, and
catalogues written before the queue columns existed gain them.

Connection errors surface as :class:`CatalogUnavailable` (a ``ConnectionError``,
so the API answers 503), a full database disk as ``OSError(ENOSPC)`` (507).
"""

from __future__ import annotations

import errno
import json
import math
import os
import secrets
import socket
import sqlite3
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

__all__ = ["Catalog", "CatalogUnavailable", "Claim", "MeshRecord", "Status", "MAX_LOST",
           "new_owner", "open_catalog", "redact_url"]

# Builders that may vanish (lease expired) before a mesh is failed instead of claimed again.
MAX_LOST = 3


class Status(str, Enum):
    QUEUED = "queued"
    BUILDING = "building"
    READY = "ready"
    FAILED = "failed"


@dataclass(frozen=True)
class MeshRecord:
    """One catalogue row.

    summary : ``ProgressiveMesh.summary()`` without its metadata (counts and the
    error curve) once ready, else empty. ``digest`` is the artefact's SHA-256,
    the seed of every ETag served from it and part of its key in the store.
    ``attempt`` counts the claims of its build (the fencing token of the latest).
    """

    id: str
    name: str
    status: Status
    progress: float
    file_type: str
    source_bytes: int
    options: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)
    failure: str | None = None
    digest: str | None = None
    created: float = 0.0
    updated: float = 0.0
    attempt: int = 0


@dataclass(frozen=True)
class Claim:
    """A build held under a lease: the row as claimed and who holds it."""

    record: MeshRecord
    owner: str

    @property
    def mesh_id(self) -> str:
        return self.record.id

    @property
    def attempt(self) -> int:
        return self.record.attempt


class CatalogUnavailable(ConnectionError):
    """The catalogue's database cannot be reached; the message names it without credentials."""


def new_owner(node: str) -> str:
    """A lease owner name: the node (one data directory) and this process's incarnation."""
    return f"{node}/{socket.gethostname()[:32]}.{os.getpid()}.{secrets.token_hex(3)}"


@dataclass(frozen=True)
class Dialect:
    """What differs between the two databases; everything else is shared SQL.

    now : an expression for the database's clock in seconds since the epoch
    (every lease is computed on it, never on a host's clock).
    """

    placeholder: str
    real: str
    integer: str
    now: str
    skip_locked: str


DIALECTS = {
    "sqlite": Dialect(placeholder="?", real="REAL", integer="INTEGER",
                      now="((julianday('now') - 2440587.5) * 86400.0)", skip_locked=""),
    "postgresql": Dialect(placeholder="%s", real="DOUBLE PRECISION", integer="BIGINT",
                          now="EXTRACT(EPOCH FROM clock_timestamp())::float8",
                          skip_locked="FOR UPDATE SKIP LOCKED"),
}

COLUMNS = ("id", "name", "status", "progress", "file_type", "source_bytes", "options", "summary",
           "failure", "digest", "created", "updated", "attempt")
_SELECT = ", ".join(COLUMNS)
# Added after the first catalogues were written: opening an older one adds them.
_QUEUE_COLUMNS = {"attempt": "INTEGER NOT NULL DEFAULT 0", "lease_owner": "TEXT",
                  "lease_until": "{real}", "lost": "INTEGER NOT NULL DEFAULT 0"}
_TABLE = """CREATE TABLE IF NOT EXISTS meshes (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    status TEXT NOT NULL,
    progress {real} NOT NULL,
    file_type TEXT NOT NULL,
    source_bytes {integer} NOT NULL,
    options TEXT NOT NULL,
    summary TEXT NOT NULL,
    failure TEXT,
    digest TEXT,
    created {real} NOT NULL,
    updated {real} NOT NULL
)"""
_INDEXES = ("CREATE INDEX IF NOT EXISTS meshes_created ON meshes (created)",
            "CREATE INDEX IF NOT EXISTS meshes_queue ON meshes (status, created)")
# Rows a claim may take: queued, or building under a lease that ran out (or
# never had one: a catalogue from before leases, or Store.mark_building).
_CLAIMABLE = ("(status = 'queued' OR (status = 'building' AND (lease_until IS NULL "
              "OR lease_until < {now})))")
_FENCE = "attempt = ? AND status = 'building'"


class Catalog(ABC):
    """The rows of meshes and their build queue; keyword-only methods, no files, no HTTP.

    Methods returning a row return None when no row matched (an unknown id, or
    a fenced write whose claim is no longer current). Safe from several threads.
    """

    dialect: Dialect

    def __init__(self):
        d = self.dialect
        now = d.now
        claimable = _CLAIMABLE.format(now=now)
        self._sql = {
            "insert": f"INSERT INTO meshes ({_SELECT}) VALUES ({', '.join('?' * len(COLUMNS))})",
            "get": f"SELECT {_SELECT} FROM meshes WHERE id = ?",
            "list": f"SELECT {_SELECT} FROM meshes ORDER BY created DESC, id LIMIT ? OFFSET ?",
            "delete": f"DELETE FROM meshes WHERE id = ? RETURNING {_SELECT}",
            "claim": (f"UPDATE meshes SET status = 'building', attempt = attempt + 1, "
                      f"lease_owner = ?, lease_until = {now} + ?, progress = 0.0, failure = NULL, "
                      "lost = lost + (CASE WHEN status = 'building' THEN 1 ELSE 0 END), "
                      f"updated = ? WHERE id = (SELECT id FROM meshes WHERE {claimable}{{only}} "
                      f"ORDER BY created, id LIMIT 1 {d.skip_locked}) AND {claimable} "
                      f"RETURNING {_SELECT}"),
            # lost counts builders already gone; an expired lease is one more
            "abandon": (f"UPDATE meshes SET status = 'failed', failure = ?, lease_owner = NULL, "
                        f"lease_until = NULL, updated = ? WHERE (status = 'building' AND "
                        f"lease_until < {now} AND lost + 1 >= ?) OR (status = 'queued' AND "
                        f"lost >= ?) RETURNING {_SELECT}"),
            "renew": f"UPDATE meshes SET lease_until = {now} + ? WHERE id = ? AND {_FENCE}",
            "recover": (f"UPDATE meshes SET status = 'queued', progress = 0.0, lease_owner = NULL, "
                        "lease_until = NULL, lost = lost + 1, updated = ? WHERE status = "
                        "'building' AND (lease_owner IS NULL OR substr(lease_owner, 1, ?) = ?) "
                        f"RETURNING {_SELECT}"),
            "pending": (f"SELECT {_SELECT} FROM meshes WHERE status = 'queued' "
                        "ORDER BY created, id"),
            "ahead": ("SELECT COUNT(*) FROM meshes WHERE status = 'queued' AND "
                      "(created < ? OR (created = ? AND id < ?))"),
            "held": ("SELECT COALESCE(SUM(source_bytes), 0) FROM meshes WHERE status IN "
                     "('queued', 'building')"),
            "artefacts": "SELECT id, file_type, status, digest FROM meshes",
            "lease": "SELECT lease_owner, lease_until FROM meshes WHERE id = ?",
        }
        if d.placeholder != "?":
            self._sql = {name: sql.replace("?", d.placeholder) for name, sql in self._sql.items()}

    # ---- what each database does its own way ---------------------------------
    @abstractmethod
    def _run(self, sql: str, params=()) -> tuple[list[tuple], int]:
        """Execute one statement (autocommit); its rows and its row count."""

    @abstractmethod
    def _create_schema(self) -> None:
        """Create the table and indexes, and add missing columns, under a lock."""

    @abstractmethod
    def ping(self, *, timeout: float) -> None:
        """Return once the database answers a trivial query, within about ``timeout``
        seconds; raise (:class:`CatalogUnavailable`, ``sqlite3.Error``, OSError) if it
        cannot. The readiness probe: cheap, and never queued behind the builds."""

    def close(self) -> None:
        """Close the connections."""

    # ---- rows -----------------------------------------------------------------
    def insert(self, record: MeshRecord) -> None:
        self._run(self._sql["insert"], _row_of(record))

    def get(self, *, mesh_id: str) -> MeshRecord | None:
        rows, _ = self._run(self._sql["get"], (mesh_id,))
        return _record(rows[0]) if rows else None

    def list(self, *, limit: int, offset: int) -> list[MeshRecord]:
        rows, _ = self._run(self._sql["list"], (int(limit), int(offset)))
        return [_record(row) for row in rows]

    def delete(self, *, mesh_id: str) -> MeshRecord | None:
        """Remove the row; the row removed, or None."""
        rows, _ = self._run(self._sql["delete"], (mesh_id,))
        return _record(rows[0]) if rows else None

    def update(self, *, mesh_id: str, values: dict, updated: float,
               attempt: int | None = None) -> MeshRecord | None:
        """Set ``values`` (column -> value; dicts stored as JSON) on the row.

        ``attempt`` fences the write: it only happens while the row is building
        under that claim. The row after the write, or None if none matched.
        """
        values = {key: json.dumps(value) if isinstance(value, dict) else value
                  for key, value in values.items()}
        values["updated"] = updated
        assignments = ", ".join(f"{key} = ?" for key in values)
        sql = f"UPDATE meshes SET {assignments} WHERE id = ?"
        params = [*values.values(), mesh_id]
        if attempt is not None:
            sql += f" AND {_FENCE}"
            params.append(int(attempt))
        sql = (sql + f" RETURNING {_SELECT}").replace("?", self.dialect.placeholder)
        rows, _ = self._run(sql, params)
        return _record(rows[0]) if rows else None

    # ---- the queue ----------------------------------------------------------------
    def claim(self, *, owner: str, lease_seconds: float, updated: float,
              mesh_id: str | None = None) -> Claim | None:
        """Take the oldest claimable row (or only ``mesh_id``) under a new lease."""
        only = "" if mesh_id is None else f" AND id = {self.dialect.placeholder}"
        sql = self._sql["claim"].replace("{only}", only)
        params = [owner, float(lease_seconds), updated] + ([mesh_id] if mesh_id else [])
        rows, _ = self._run(sql, params)
        return Claim(_record(rows[0]), owner) if rows else None

    def abandon(self, *, max_lost: int, reason: str, updated: float) -> list[MeshRecord]:
        """Fail the rows whose builder vanished ``max_lost`` times (the last one's
        lease expired, or it was requeued by ``recover``): a mesh that kills
        whatever builds it is not passed around forever."""
        rows, _ = self._run(self._sql["abandon"], (reason, updated, int(max_lost),
                                                   int(max_lost)))
        return [_record(row) for row in rows]

    def renew(self, *, claim: Claim, lease_seconds: float) -> bool:
        """Extend the lease of ``claim``; False if it is no longer current (taken over,
        deleted, or settled)."""
        _, count = self._run(self._sql["renew"], (float(lease_seconds), claim.mesh_id,
                                                  claim.attempt))
        return count > 0

    def recover(self, *, node: str, updated: float) -> list[MeshRecord]:
        """Requeue the building rows of an earlier incarnation of ``node`` (whose lease
        cannot be held by anyone alive: one process per node) and rows with no lease."""
        prefix = f"{node}/"
        rows, _ = self._run(self._sql["recover"], (updated, len(prefix), prefix))
        return [_record(row) for row in rows]

    def lease(self, *, mesh_id: str) -> tuple[str | None, float | None] | None:
        """(owner, expiry in seconds since the epoch) of a row's lease, (None, None)
        when it has none; None for an unknown id. Who builds what, for operators."""
        rows, _ = self._run(self._sql["lease"], (mesh_id,))
        return tuple(rows[0]) if rows else None

    def pending(self) -> list[MeshRecord]:
        """Queued rows, oldest first."""
        rows, _ = self._run(self._sql["pending"])
        return [_record(row) for row in rows]

    def queued_before(self, record: MeshRecord) -> int:
        """How many queued rows a claim takes before ``record`` (claims go oldest first)."""
        rows, _ = self._run(self._sql["ahead"], (record.created, record.created, record.id))
        return int(rows[0][0])

    def held_source_bytes(self) -> int:
        """Sum of ``source_bytes`` over the queued and building rows (their sources
        are kept until the build is done)."""
        rows, _ = self._run(self._sql["held"])
        return int(rows[0][0])

    def artefacts(self) -> list[tuple[str, str, str, str | None]]:
        """(id, file_type, status, digest) of every row: what the store's files should be."""
        rows, _ = self._run(self._sql["artefacts"])
        return [tuple(row) for row in rows]

    # ---- schema -------------------------------------------------------------------
    def _schema_statements(self, existing: set[str]) -> list[str]:
        d = self.dialect
        statements = [_TABLE.format(real=d.real, integer=d.integer)]
        statements += [f"ALTER TABLE meshes ADD COLUMN {name} {kind.format(real=d.real)}"
                       for name, kind in _QUEUE_COLUMNS.items() if name not in existing]
        return statements + list(_INDEXES)


class SqliteCatalog(Catalog):
    """The embedded catalogue: a SQLite file in WAL mode (several processes of one
    machine may share it; never on a network filesystem, whose locks SQLite cannot trust).

    One connection shared by threads, serialised by a lock: writes are small
    and rare next to builds, and SQLite serialises writers anyway. Another
    process's write lock is waited for up to ``busy_seconds``.
    """

    dialect = DIALECTS["sqlite"]

    def __init__(self, path, *, busy_seconds: float = 30.0):
        super().__init__()
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.RLock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None,
                                   timeout=busy_seconds)
        _switch_to_wal(self._db, busy_seconds)
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._create_schema()

    def _run(self, sql, params=()):
        with self._lock:
            cursor = self._db.execute(sql, tuple(params))
            rows = cursor.fetchall()
            return rows, (cursor.rowcount if cursor.rowcount >= 0 else len(rows))

    def ping(self, *, timeout: float) -> None:
        # a read of the table, not SELECT 1, which SQLite answers without the file;
        # the shared connection held longer than the timeout counts as a failure
        if not self._lock.acquire(timeout=timeout):
            raise CatalogUnavailable(f"the catalogue was busy for {timeout:g} s")
        try:
            self._db.execute("SELECT 1 FROM meshes LIMIT 1").fetchall()
        finally:
            self._lock.release()

    def _create_schema(self) -> None:
        with self._lock:
            # IMMEDIATE: the write lock first, so two processes opening a new
            # file at once create it one after the other
            self._db.execute("BEGIN IMMEDIATE")
            try:
                existing = {row[1] for row in self._db.execute("PRAGMA table_info(meshes)")}
                for statement in self._schema_statements(existing):
                    self._db.execute(statement)
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise

    def close(self) -> None:
        with self._lock:
            self._db.close()


def _switch_to_wal(db: sqlite3.Connection, busy_seconds: float) -> None:
    """Put the file in WAL mode, waiting up to ``busy_seconds`` for other openers.

    The switch takes the file's exclusive lock and, unlike other statements,
    answers "database is locked" at once instead of calling the busy handler
    when another connection holds any lock: several processes opening a new
    file at once would fail at random. So it is retried, with a growing pause,
    until the file is in WAL mode (switched by whichever opener got the lock
    first) or the wait is over. A file already in WAL mode needs no lock.
    """
    deadline = time.monotonic() + busy_seconds
    pause = 0.002
    while True:
        try:
            if db.execute("PRAGMA journal_mode").fetchone()[0].lower() == "wal":
                return
            if db.execute("PRAGMA journal_mode=WAL").fetchone()[0].lower() == "wal":
                return
            reason = "the file did not switch to WAL mode"
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) and "busy" not in str(exc):
                raise
            reason = str(exc)
        if time.monotonic() >= deadline:
            raise sqlite3.OperationalError(f"{reason} (waited {busy_seconds:g} s for other "
                                           "openers)")
        time.sleep(pause)
        pause = min(2 * pause, 0.05)


# The longest a PostgreSQL call waits for its answer (seconds), in this process:
# a server that accepts connections but never answers (a stalled proxy, a
# partition that drops packets one way) would otherwise hold a thread, a
# build runner's queue poll say, for ever, and with it the shutdown. Every
# statement here is a single-row read or write, answered in milliseconds
# by a working server, so a wait this long means the server is unreachable.
ANSWER_SECONDS = 20.0
# libpq's TCP settings for every connection: keepalives notice a peer that
# vanished while the connection idled in the pool, TCP_USER_TIMEOUT a write
# that goes unacknowledged (milliseconds).
_TCP_OPTIONS = {"keepalives": 1, "keepalives_idle": 10, "keepalives_interval": 5,
                "keepalives_count": 3, "tcp_user_timeout": int(ANSWER_SECONDS * 1000)}


def _bounded_connection_class(psycopg):
    """A psycopg Connection whose every wait for the server ends after
    :data:`ANSWER_SECONDS` (psycopg's own waits have no deadline; its timeout
    error is an OperationalError, which the catalogue reports as unavailable)."""

    class BoundedConnection(psycopg.Connection):
        def wait(self, gen, interval=0.1, timeout=None):
            try:
                return super().wait(gen, interval=interval, timeout=timeout or ANSWER_SECONDS)
            except psycopg.OperationalError:
                # the protocol is mid-exchange: the connection cannot be reused
                self.pgconn.finish()
                raise

    return BoundedConnection


class PostgresCatalog(Catalog):
    """A catalogue on a PostgreSQL server (psycopg 3), shared by any number of processes.

    A small pool of autocommit connections (``connections`` at most per process,
    opened on demand): every operation is one statement, and a server's threads
    need not queue behind one connection. A connection found broken is dropped and
    the statement retried once on a new one (the server restarted meanwhile).
    """

    dialect = DIALECTS["postgresql"]

    def __init__(self, url: str, *, connections: int = 4, connect_seconds: float = 10.0):
        try:
            import psycopg
        except ImportError:
            raise CatalogUnavailable("a PostgreSQL catalogue needs the psycopg package: "
                                     "pip install 'lodserver[distributed]'") from None
        self._psycopg = psycopg
        self._connection_class = _bounded_connection_class(psycopg)
        super().__init__()
        self.url = url
        self._connect_seconds = connect_seconds
        self._idle: list = []
        self._lock = threading.Lock()
        self._slots = threading.BoundedSemaphore(max(1, connections))
        self._closed = False
        # the readiness probe's own connection: never waits for a pool slot
        self._probe = None
        self._probe_lock = threading.Lock()
        self._create_schema()

    def _connect(self, seconds: float | None = None, **options):
        seconds = self._connect_seconds if seconds is None else seconds
        try:
            return self._connection_class.connect(
                self.url, autocommit=True, connect_timeout=max(1, math.ceil(seconds)),
                **{**_TCP_OPTIONS, **options})
        except self._psycopg.OperationalError as exc:
            raise CatalogUnavailable(f"cannot reach the catalogue at {redact_url(self.url)}: "
                                     f"{_first_line(exc)}") from None

    def _run(self, sql, params=()):
        psycopg = self._psycopg
        with self._slots:
            for retry in (True, False):
                with self._lock:
                    connection = self._idle.pop() if self._idle else None
                pooled = connection is not None
                connection = connection or self._connect()
                try:
                    cursor = connection.execute(sql, tuple(params))
                    rows = cursor.fetchall() if cursor.description else []
                    count = cursor.rowcount
                except psycopg.errors.DiskFull:
                    self._give_back(connection)
                    raise OSError(errno.ENOSPC, "the catalogue's disk is full") from None
                except psycopg.OperationalError as exc:
                    connection.close()
                    if retry and pooled:
                        continue        # a stale pooled connection: once more on a new one
                    raise CatalogUnavailable(f"the catalogue at {redact_url(self.url)} failed: "
                                             f"{_first_line(exc)}") from None
                except BaseException:
                    self._give_back(connection)
                    raise
                self._give_back(connection)
                return rows, count
        raise AssertionError("unreachable")

    def ping(self, *, timeout: float) -> None:
        """``SELECT 1`` on a connection kept for the probe; a broken one is replaced
        once (the server restarted since). ``timeout`` bounds the connection and,
        through TCP_USER_TIMEOUT, a query whose packets go unanswered."""
        psycopg = self._psycopg
        with self._probe_lock:
            if self._probe is not None:
                try:
                    self._probe.execute("SELECT 1")
                    return
                except psycopg.Error:
                    self._probe.close()
                    self._probe = None
            connection = self._connect(timeout, tcp_user_timeout=math.ceil(timeout * 1000))
            try:
                connection.execute("SELECT 1")
            except psycopg.Error as exc:
                connection.close()
                raise CatalogUnavailable(f"the catalogue at {redact_url(self.url)} failed: "
                                         f"{_first_line(exc)}") from None
            if self._closed:
                connection.close()
            else:
                self._probe = connection

    def _give_back(self, connection) -> None:
        with self._lock:
            if self._closed or connection.closed:
                connection.close()
            else:
                self._idle.append(connection)

    def _create_schema(self) -> None:
        # CREATE TABLE IF NOT EXISTS is not safe against a concurrent creator in
        # PostgreSQL (a unique violation in pg_type): serialise on an advisory lock.
        connection = self._connect()
        try:
            with connection.transaction():
                connection.execute("SELECT pg_advisory_xact_lock(7140314)")
                existing = {row[0] for row in connection.execute(
                    "SELECT column_name FROM information_schema.columns WHERE "
                    "table_name = 'meshes' AND table_schema = current_schema()")}
                for statement in self._schema_statements(existing):
                    connection.execute(statement)
        except self._psycopg.OperationalError as exc:
            raise CatalogUnavailable(f"the catalogue at {redact_url(self.url)} failed: "
                                     f"{_first_line(exc)}") from None
        finally:
            connection.close()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        # a probe stuck on an unanswering server holds the lock: its connection
        # is then left to the process's exit rather than waited for
        if self._probe_lock.acquire(timeout=1.0):
            try:
                if self._probe is not None:
                    idle.append(self._probe)
                    self._probe = None
            finally:
                self._probe_lock.release()
        for connection in idle:
            connection.close()


def open_catalog(url: str | None, *, data_dir) -> Catalog:
    """The catalogue named by ``url``.

    None or empty: ``catalogue.sqlite3`` in ``data_dir`` (the embedded default);
    ``sqlite:///abs/path.sqlite3`` or ``sqlite://rel/path``: that SQLite file;
    ``postgresql://user:password@host:port/database`` (or ``postgres://``): PostgreSQL.
    Raises ValueError for any other scheme, :class:`CatalogUnavailable` when the
    database cannot be reached.
    """
    if not url:
        return SqliteCatalog(Path(data_dir) / "catalogue.sqlite3")
    scheme = url.split(":", 1)[0].lower() if ":" in url else ""
    if scheme == "sqlite":
        path = url.split(":", 1)[1]
        path = path[2:] if path.startswith("//") else path
        if not path:
            raise ValueError("a sqlite: catalogue URL names its file, as in "
                             "sqlite:///var/lib/lodserver/catalogue.sqlite3")
        return SqliteCatalog(Path(path))
    if scheme in ("postgresql", "postgres"):
        return PostgresCatalog(url)
    raise ValueError(f"the catalogue URL must start with postgresql:// or sqlite://, not "
                     f"{redact_url(url)!r}")


def redact_url(url: str) -> str:
    """``url`` without its password (for messages and logs)."""
    try:
        parts = urlsplit(url)
    except ValueError:
        return "the configured URL"
    if parts.password is None:
        return url
    netloc = parts.netloc.rsplit("@", 1)
    user = (parts.username or "") + ":***"
    return urlunsplit(parts._replace(netloc=f"{user}@{netloc[-1]}"))


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _row_of(record: MeshRecord) -> tuple:
    values = []
    for name in COLUMNS:
        value = getattr(record, name)
        if isinstance(value, Status):
            value = value.value
        elif isinstance(value, dict):
            value = json.dumps(value)
        values.append(value)
    return tuple(values)


def _record(row) -> MeshRecord:
    values = dict(zip(COLUMNS, row))
    values["status"] = Status(values["status"])
    values["options"] = json.loads(values["options"])
    values["summary"] = json.loads(values["summary"])
    return MeshRecord(**values)
