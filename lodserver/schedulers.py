"""Where the assets of a folder export run: a local thread pool or a Dask cluster.

``pipeline.export_folder`` hands each asset to a scheduler as one task (a
picklable function of one picklable argument) and takes the outcomes back as
they finish, in completion order, so its progress bar and per-asset lines read
the same whichever runs them:

- ``None`` (the default): a pool of ``jobs`` threads in this process (the
  compiled kernels release the GIL);
- ``"local"``: a Dask ``LocalCluster`` of ``jobs`` worker processes with one
  thread each, started here and closed after;
- ``"tcp://HOST:PORT"`` (any Dask address): the cluster whose scheduler listens
  there; ``jobs`` does not apply (every worker thread takes tasks);
- a ``distributed.Client``: that client's cluster, left open after.

Dask re-runs the tasks of a worker that is lost mid-task on another worker
(up to its ``distributed.scheduler.allowed-failures``), so a task must be
idempotent: ``pipeline.export_asset`` writes each output whole (a rename, or
one object-store PUT) and leaves the manifest to the client.

Dask is imported only when it is asked for: the plain install has none, and
then a scheduler other than ``None`` is a :class:`SchedulerError` naming the
extra to install.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import contextmanager

from .mesh import MeshError

DISTRIBUTED_EXTRA = "pip install 'lodserver[distributed]'"
# How long to wait for a scheduler that does not answer before saying so.
CONNECT_SECONDS = 10


class SchedulerError(MeshError):
    """A scheduler cannot be used: Dask missing, a bad address, a cluster that does not answer."""


def check_scheduler(scheduler) -> None:
    """Refuse what :func:`open_scheduler` could never use, before any work starts."""
    if scheduler is None or _is_client(scheduler):
        return
    if scheduler == "local":
        _import_distributed()
        return
    if not isinstance(scheduler, str) or "://" not in scheduler:
        raise SchedulerError(f"the scheduler must be 'local' or a Dask address such as "
                             f"tcp://127.0.0.1:8786, got {scheduler!r}")
    _import_distributed()       # missing Dask is said at once, even with nothing to build


@contextmanager
def open_scheduler(scheduler=None, *, jobs: int = 1):
    """A running scheduler (see the module docstring), closed on exit if opened here.

    Yields an object with ``submit(function, argument, key) -> future`` and
    ``completed(futures)``, an iterator over the futures as they finish, and
    ``outcome(future)``, the task's return value or the exception that ended it.
    """
    check_scheduler(scheduler)
    if scheduler is None:
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            yield _Threads(pool)
        return
    distributed = _import_distributed()
    if _is_client(scheduler):
        yield _Dask(scheduler, distributed)
        return
    if scheduler == "local":
        # processes, one thread each: the same shape as `dask worker --nthreads 1`; on
        # loopback only, and no dashboards. The scheduler's HTTP server (health
        # routes) starts even so, on 8787 unless told: any free port instead, as
        # 8787 may be taken by another cluster.
        cluster = distributed.LocalCluster(
            n_workers=jobs, threads_per_worker=1, processes=True, host="127.0.0.1",
            dashboard_address=None, worker_dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
        try:
            with distributed.Client(cluster) as client:
                yield _Dask(client, distributed)
        finally:
            cluster.close()
        return
    try:
        client = distributed.Client(scheduler, timeout=CONNECT_SECONDS)
    except (OSError, TimeoutError, ValueError) as exc:
        raise SchedulerError(f"cannot reach the Dask scheduler at {scheduler} "
                             f"({type(exc).__name__}: {exc})") from None
    with client:
        yield _Dask(client, distributed)


class _Threads:
    def __init__(self, pool: ThreadPoolExecutor):
        self.pool = pool

    def submit(self, function, argument, key: str):
        return self.pool.submit(function, argument)

    def completed(self, futures):
        return as_completed(futures)

    def outcome(self, future):
        try:
            return future.result()
        except Exception as exc:        # reported by the caller, for that asset alone
            return exc


class _Dask:
    def __init__(self, client, distributed):
        self.client, self.distributed = client, distributed

    def submit(self, function, argument, key: str):
        # pure=False: a rerun of the same asset is a new task, never a cached result
        return self.client.submit(function, argument, key=key, pure=False, retries=0)

    def completed(self, futures):
        return self.distributed.as_completed(futures)

    def outcome(self, future):
        try:
            return future.result()
        except Exception as exc:        # KilledWorker, a worker that cannot import lodserver
            return exc
        finally:
            future.release()


def _is_client(scheduler) -> bool:
    # a Client without importing distributed (absent in the plain install)
    return type(scheduler).__name__ == "Client" and hasattr(scheduler, "submit")


def _import_distributed():
    try:
        import distributed
    except ImportError:
        raise SchedulerError(f"running on Dask needs the distributed extra: "
                             f"{DISTRIBUTED_EXTRA}") from None
    return distributed
