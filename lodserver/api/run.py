"""The two long-running commands: ``lodserver serve`` (the HTTP service) and
``lodserver worker`` (builds from the shared queue, serving nothing).

Both read their settings from the ``LODSERVER_*`` variables (``api.settings``)
and check them, and the catalogue and store they name, before starting: a wrong
URL or an unreachable database is one sentence on stderr and exit code 1, not a
traceback from inside uvicorn or a worker thread.
"""

from __future__ import annotations

import os
import sys


def server_settings(data=None):
    """The ``LODSERVER_*`` settings (``data``, when given, is ``LODSERVER_DATA_DIR``),
    and the store they name opened once as a check: ``(settings, None)``, or
    ``(None, one sentence)`` when a variable is invalid or the catalogue, the store or
    the data directory is unusable."""
    from pydantic import ValidationError

    from ..service.catalog import CatalogUnavailable
    from ..service.store import StoreError
    from .main import open_store
    from .settings import Settings

    if data is not None:
        os.environ["LODSERVER_DATA_DIR"] = str(data)
    try:
        settings = Settings()
    except ValidationError as exc:
        # pydantic's own text repeats the value, which may hold a password
        return None, "; ".join(f"LODSERVER_{'_'.join(map(str, e['loc'])).upper()}: "
                               f"{e['msg'].removeprefix('Value error, ')}" for e in exc.errors())
    try:
        open_store(settings).close()
    except (CatalogUnavailable, StoreError, ValueError) as exc:
        return None, str(exc)
    return settings, None


def serve(*, data=None, host: str, port: int, log_level: str) -> int:
    """Run the HTTP API and the viewer until stopped; the exit code."""
    import uvicorn

    from .protocol import head_deadline_protocol

    settings, problem = server_settings(data)
    if problem:
        print(f"lodserver serve: {problem}", file=sys.stderr)
        return 1
    uvicorn.run("lodserver.api.main:create_app", factory=True, host=host, port=port,
                log_level=log_level, http=head_deadline_protocol(settings.header_seconds))
    return 0


def work(*, data=None, workers: int | None = None, log_level: str) -> int:
    """Build from the shared queue until SIGTERM or SIGINT (builds under way go back
    to the queue); the exit code."""
    import logging
    import signal
    import threading

    from ..service.catalog import redact_url
    from ..service.parsing import ParsePool
    from .main import build_runner, open_store

    if workers is not None:
        os.environ["LODSERVER_WORKERS"] = str(workers)
    settings, problem = server_settings(data)
    if problem is None and settings.workers == 0:
        problem = "a worker with 0 builds at a time would do nothing; pass --workers 1 or more"
    if problem:
        print(f"lodserver worker: {problem}", file=sys.stderr)
        return 1
    logging.basicConfig(level=log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    store = open_store(settings)
    parser = ParsePool(workers=settings.parse_workers, queue=settings.parse_queue,
                       memory_bytes=settings.parse_memory_bytes)
    runner = build_runner(store, settings, parser)
    try:
        runner.start(warm=settings.warm_kernels)
        where = redact_url(settings.catalog_url) if settings.catalog_url else "the data directory"
        print(f"lodserver worker: building from the queue of {where}, {settings.workers} at a "
              "time; Ctrl-C or SIGTERM stops it (builds under way go back to the queue)",
              file=sys.stderr, flush=True)
        while not stop.wait(1.0):
            pass
    finally:
        runner.shutdown()
        store.close()
    return 0
