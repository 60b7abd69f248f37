"""``LODSERVER_TOKEN_FILE``: the bearer token read from a file (a Docker or
Kubernetes secret), through the real app and real ``lodserver serve`` processes:
the file's token guards the writes, its trailing newline is not part of it, and
a server given both variables, or a file it cannot use, refuses to start with
exit code 1 and one sentence."""

import os
import subprocess
import sys

import httpx
import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.settings import Settings

from ..meshes import DATA
from ..server import _free_port, server_process

SPOT = (DATA / "spot.obj").read_bytes()
TOKEN = "file-s3cret"


def _upload(post, token=None):
    headers = {"Authorization": f"Bearer {token}"} if token is not None else {}
    return post("/meshes", files={"file": ("spot.obj", SPOT)}, headers=headers)


def test_the_token_in_the_file_guards_the_writes_without_its_newline(tmp_path):
    secret = tmp_path / "token"
    secret.write_text(TOKEN + "\n")
    settings = Settings(data_dir=tmp_path / "data", warm_kernels=False, token_file=secret)
    with TestClient(create_app(settings)) as client:
        assert _upload(client.post).status_code == 401
        # a header's trailing whitespace never reaches the app: compare the setting
        assert client.app.state.settings.token.get_secret_value() == TOKEN
        created = _upload(client.post, TOKEN)
        assert created.status_code == 202, created.text
        mesh_id = created.json()["id"]
        assert client.delete(f"/meshes/{mesh_id}").status_code == 401
        assert client.delete(f"/meshes/{mesh_id}",
                             headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 204


def test_a_served_process_reads_its_token_from_the_file(tmp_path):
    secret = tmp_path / "token"
    secret.write_text(TOKEN + "\r\n")
    with server_process(tmp_path / "data", env={"LODSERVER_TOKEN_FILE": str(secret)}) \
            as (base, _), httpx.Client(base_url=base, timeout=60) as client:
        assert _upload(client.post).status_code == 401
        assert _upload(client.post, TOKEN).status_code == 202


def _serve_refused(tmp_path, env: dict) -> str:
    """Run ``lodserver serve`` with ``env``; assert it exits 1 before serving, and
    return what it printed."""
    done = subprocess.run(
        [sys.executable, "-m", "lodserver.cli", "serve", "--data", str(tmp_path / "data"),
         "--port", str(_free_port())],
        env={**os.environ, "LODSERVER_TOKEN": "", "LODSERVER_WARM_KERNELS": "false", **env},
        capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lodserver serve: "), done.stderr
    return lines[0]


@pytest.mark.parametrize("problem", ["both", "missing", "folder", "empty", "binary"])
def test_a_token_file_that_cannot_be_used_stops_the_start(tmp_path, problem):
    secret = tmp_path / "token"
    env = {"LODSERVER_TOKEN_FILE": str(secret)}
    if problem == "both":
        secret.write_text(TOKEN)
        env["LODSERVER_TOKEN"] = "another"
    elif problem == "folder":
        secret.mkdir()
    elif problem == "empty":
        secret.write_text("\n")
    elif problem == "binary":
        secret.write_bytes(b"\xff\xfe\x00token")
    message = _serve_refused(tmp_path, env)
    expected = {"both": "set LODSERVER_TOKEN or LODSERVER_TOKEN_FILE, not both",
                "missing": "(No such file or directory)", "folder": "(Is a directory)",
                "empty": "is empty", "binary": "is not UTF-8 text"}[problem]
    assert expected in message, message
    assert TOKEN not in message and "another" not in message
    assert not (tmp_path / "data").exists()     # refused before anything was created
