"""docker/Dockerfile's own CMD and HEALTHCHECK, run as the image runs them
(without Docker): the check follows ``LODSERVER_PORT``, the port the CMD serves
on, and fails while ``/readyz`` does; the CMD's shell hands SIGTERM to the server."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .server import _free_port

DOCKERFILE = Path(__file__).resolve().parents[1] / "docker" / "Dockerfile"


def _instruction(name: str) -> list[str]:
    """The exec-form argument list of the Dockerfile's ``name`` instruction
    (HEALTHCHECK: the list after its CMD), continuation lines joined."""
    text = DOCKERFILE.read_text().replace("\\\n", " ")
    line = next(line for line in text.splitlines() if line.startswith(name + " "))
    return json.loads(line[line.index("["):])


@pytest.fixture
def image_env(tmp_path):
    """The environment the image gives its commands: ``lodserver`` on PATH (this
    checkout's), the data directory, and a port that is not the default."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "lodserver"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m lodserver.cli "$@"\n')
    shim.chmod(0o755)
    return {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
            "PYTHONPATH": str(DOCKERFILE.parents[1]), "LODSERVER_PORT": str(_free_port()),
            "LODSERVER_DATA_DIR": str(tmp_path / "data"),
            "LODSERVER_STORE_URL": str(tmp_path / "store"), "LODSERVER_TOKEN": "",
            "LODSERVER_WARM_KERNELS": "false"}


def _check(env) -> subprocess.CompletedProcess:
    command = _instruction("HEALTHCHECK")
    assert command[0] == "python"
    return subprocess.run([sys.executable, *command[1:]], env=env, capture_output=True,
                          text=True, timeout=30)


def _until_check(env, healthy: bool, timeout: float = 60) -> subprocess.CompletedProcess:
    deadline = time.monotonic() + timeout
    while (done := _check(env)).returncode != (0 if healthy else 1):
        assert time.monotonic() < deadline, done.stderr
        time.sleep(0.5)
    return done


def test_the_healthcheck_asks_readyz_on_the_port_the_cmd_serves(image_env, tmp_path):
    assert _check(image_env).returncode == 1        # nothing listens yet
    # a session of its own: should the test fail, the whole group is killed
    server = subprocess.Popen(_instruction("CMD"), env=image_env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        _until_check(image_env, healthy=True)
        # another port is another server: the check does not pass by accident
        assert _check({**image_env, "LODSERVER_PORT": str(_free_port())}).returncode == 1

        store = tmp_path / "store"
        for child in store.iterdir():
            child.rmdir()
        store.rmdir()
        failed = _until_check(image_env, healthy=False)
        assert "503" in failed.stderr and failed.stderr.startswith("not ready: ")
        store.mkdir()
        _until_check(image_env, healthy=True)

        # exec: the container's first process is the server itself, not a shell
        # that would take docker stop's SIGTERM and leave the server running
        command_line = Path(f"/proc/{server.pid}/cmdline").read_bytes().split(b"\0")
        assert b"lodserver.cli" in command_line and b"serve" in command_line
        server.send_signal(signal.SIGTERM)
        server.wait(30)
        assert server.returncode in (0, -signal.SIGTERM), server.stdout.read()
        assert _check(image_env).returncode == 1
    finally:
        try:
            os.killpg(server.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        server.wait()
