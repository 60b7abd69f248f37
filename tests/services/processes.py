"""Stopping the processes the tests start (servers, clusters): politely first,
then by force, so that a test run never leaves one behind."""

from __future__ import annotations

import subprocess
from collections.abc import Iterable


def stop_processes(processes: Iterable[subprocess.Popen], grace: float) -> None:
    """Terminate each of ``processes`` still running, in the order given, then give
    each up to ``grace`` seconds to exit and kill the ones that did not."""
    processes = list(processes)
    for process in processes:
        if process.poll() is None:
            process.terminate()
    for process in processes:
        try:
            process.wait(grace)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
