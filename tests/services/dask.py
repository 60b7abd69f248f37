"""A Dask cluster for the tests: a scheduler and two worker processes on loopback.

Use the fixtures by importing them into a test module::

    from tests.services.dask import dask_client, dask_scheduler  # noqa: F401 (fixtures)

``dask_scheduler`` (session) is the address in ``LODSERVER_TEST_DASK_SCHEDULER``
when set (``.ci/run`` starts one cluster for the whole run through
``.ci/services/dask.sh``), else ``dask scheduler`` and two ``dask worker``
processes (one thread each, under a nanny that restarts a killed worker) this
module starts and stops after the session. The workers import lodserver from
this checkout (``PYTHONPATH``). Without dask the tests skip, and fail under
``CI=true`` (``need``).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import need
from tests.services.processes import stop_processes

SCHEDULER_VARIABLE = "LODSERVER_TEST_DASK_SCHEDULER"
CHECKOUT = Path(__file__).resolve().parents[2]
WORKERS = 2
# Starting the scheduler and importing lodserver in two workers takes seconds on a
# loaded 2-core machine.
START_TIMEOUT = 120.0


def need_distributed() -> None:
    """``need`` when dask/distributed is not installed."""
    if importlib.util.find_spec("distributed") is None:
        need("dask/distributed is not installed (pip install -e '.[distributed]')")


def worker_environment() -> dict[str, str]:
    """os.environ with this checkout first on PYTHONPATH, for worker processes."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(CHECKOUT), env.get("PYTHONPATH")]))
    return env


def start_cluster(folder: Path, workers: int = WORKERS):
    """``dask scheduler`` and ``workers`` ``dask worker`` processes on 127.0.0.1;
    returns ``(processes, address)`` once every worker has joined. The caller stops
    them (:func:`stop_cluster`)."""
    import distributed

    scheduler_file = folder / "scheduler.json"
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    processes = [subprocess.Popen(
        dask + ["--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                "--scheduler-file", str(scheduler_file)],
        stdout=subprocess.DEVNULL, stderr=(folder / "scheduler.log").open("wb"),
        env=worker_environment())]
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while not scheduler_file.is_file() or not scheduler_file.read_text().strip():
            if processes[0].poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("dask scheduler did not start")
            time.sleep(0.2)
        address = json.loads(scheduler_file.read_text())["address"]
        for index in range(workers):
            processes.append(subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", address,
                 "--nthreads", "1", "--host", "127.0.0.1", "--no-dashboard"],
                stdout=subprocess.DEVNULL, stderr=(folder / f"worker{index}.log").open("wb"),
                env=worker_environment(), cwd=folder))
        with distributed.Client(address, timeout=START_TIMEOUT) as client:
            client.wait_for_workers(workers, timeout=START_TIMEOUT)
    except BaseException:
        stop_cluster(processes)
        raise
    return processes, address


def stop_cluster(processes) -> None:
    """Stop the processes of :func:`start_cluster`, workers first (terminate, then
    kill after 20 s)."""
    stop_processes(reversed(processes), grace=20)


@pytest.fixture(scope="session")
def dask_scheduler(tmp_path_factory):
    """The address of a running Dask scheduler with two workers (module docstring)."""
    need_distributed()
    given = os.environ.get(SCHEDULER_VARIABLE)
    if given:
        yield given
        return
    processes, address = start_cluster(tmp_path_factory.mktemp("dask"))
    try:
        yield address
    finally:
        stop_cluster(processes)


@pytest.fixture
def dask_client(dask_scheduler):
    """A ``distributed.Client`` of that cluster, with both workers present."""
    import distributed

    with distributed.Client(dask_scheduler, timeout=START_TIMEOUT) as client:
        client.wait_for_workers(WORKERS, timeout=START_TIMEOUT)
        yield client
