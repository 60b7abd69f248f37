"""An S3 object store for the tests: moto's server on loopback, a fresh bucket per test.

Use the fixtures by importing them into a test module (or a conftest)::

    from tests.services.s3 import s3_endpoint, s3_url  # noqa: F401 (fixtures)

    def test_something(s3_url):          # "s3://lodserver-test-<hex>/prefix"
        ...

``s3_endpoint`` (session) is ``LODSERVER_TEST_S3_ENDPOINT`` when set (``.ci/run``
starts one server for the whole run through ``.ci/services/s3.sh``), else a
``moto_server`` this module starts on a free loopback port and stops after the
session. Without moto the tests skip, and fail under ``CI=true`` (``need``).

``s3_url`` creates an empty bucket, sets the standard AWS variables
(``AWS_ENDPOINT_URL``, credentials, region) for the test only, and removes the
bucket and its objects afterwards. :func:`s3_environment` gives the same
variables for a subprocess (a second server, a worker).
"""

from __future__ import annotations

import importlib.util
import os
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
import uuid

import pytest

from tests.conftest import need
from tests.services.processes import stop_processes

ENDPOINT_VARIABLE = "LODSERVER_TEST_S3_ENDPOINT"
# moto accepts any credentials; these only have to be present and consistent.
CREDENTIALS = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
               "AWS_DEFAULT_REGION": "us-east-1"}
# Importing moto takes several seconds on a loaded 2-core machine.
START_TIMEOUT = 60.0


def s3_environment(endpoint: str) -> dict[str, str]:
    """The AWS variables that point boto3/s3fs at ``endpoint`` (for os.environ or a
    subprocess's ``env``). The session token is cleared so a developer's real one
    is never sent to the test server."""
    return {"AWS_ENDPOINT_URL": endpoint, **CREDENTIALS, "AWS_SESSION_TOKEN": ""}


def answers(endpoint: str, timeout: float = 1.0) -> bool:
    """Whether an HTTP server answers at ``endpoint`` (any status counts)."""
    try:
        urllib.request.urlopen(endpoint, timeout=timeout).close()
    except urllib.error.HTTPError:
        return True
    except (OSError, ValueError):
        return False
    return True


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (the OS picks it; the tiny race until the
    server binds it is acceptable for tests)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def start_moto(port: int | None = None) -> tuple[subprocess.Popen, str]:
    """Start ``moto_server`` on loopback and wait until it answers; (process, endpoint).
    The caller stops it (:func:`stop_moto`)."""
    port = port or free_port()
    endpoint = f"http://127.0.0.1:{port}"
    process = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1",
                                "-p", str(port)], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + START_TIMEOUT
    while not answers(endpoint):
        if process.poll() is not None or time.monotonic() > deadline:
            stop_moto(process)
            raise RuntimeError(f"moto_server did not start on port {port}")
        time.sleep(0.2)
    return process, endpoint


def stop_moto(process: subprocess.Popen) -> None:
    """Stop a server of :func:`start_moto` (terminate, then kill after 10 s)."""
    stop_processes([process], grace=10)


@pytest.fixture(scope="session")
def s3_endpoint():
    """The URL of a running S3 server (module docstring)."""
    given = os.environ.get(ENDPOINT_VARIABLE)
    if given:
        if not answers(given, timeout=5.0):
            pytest.fail(f"{ENDPOINT_VARIABLE}={given} does not answer", pytrace=False)
        yield given
        return
    if importlib.util.find_spec("moto") is None or importlib.util.find_spec("boto3") is None:
        need("moto[server] is not installed (pip install 'moto[server]'), so no S3 server")
    process, endpoint = start_moto()
    try:
        yield endpoint
    finally:
        stop_moto(process)


@pytest.fixture
def s3_url(s3_endpoint, monkeypatch):
    """``s3://<fresh bucket>/prefix`` with the AWS variables set for this test."""
    import boto3

    for name, value in s3_environment(s3_endpoint).items():
        if value:
            monkeypatch.setenv(name, value)
        else:
            monkeypatch.delenv(name, raising=False)
    bucket = f"lodserver-test-{uuid.uuid4().hex[:16]}"
    client = boto3.client("s3", endpoint_url=s3_endpoint, **_boto_credentials())
    client.create_bucket(Bucket=bucket)
    try:
        yield f"s3://{bucket}/prefix"
    finally:
        _remove_bucket(client, bucket)


def _boto_credentials() -> dict:
    return {"aws_access_key_id": CREDENTIALS["AWS_ACCESS_KEY_ID"],
            "aws_secret_access_key": CREDENTIALS["AWS_SECRET_ACCESS_KEY"],
            "region_name": CREDENTIALS["AWS_DEFAULT_REGION"]}


def _remove_bucket(client, bucket: str) -> None:
    """Delete every object (and unfinished multipart upload) of ``bucket``, then it:
    moto keeps everything in memory for the whole session otherwise."""
    paginator = client.get_paginator("list_objects_v2")
    for page in paginator.paginate(Bucket=bucket):
        keys = [{"Key": item["Key"]} for item in page.get("Contents", [])]
        if keys:
            client.delete_objects(Bucket=bucket, Delete={"Objects": keys})
    for upload in client.list_multipart_uploads(Bucket=bucket).get("Uploads", []):
        client.abort_multipart_upload(Bucket=bucket, Key=upload["Key"],
                                      UploadId=upload["UploadId"])
    client.delete_bucket(Bucket=bucket)
