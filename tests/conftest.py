import json
import os
import shutil
import struct
from contextlib import contextmanager
from pathlib import Path

import pytest

SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"

# Under CI=true (as .ci/run is run) a test whose browser, tool or service is
# missing fails instead of skipping: a green CI then proves those tests ran.
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
# Every build compiles in the foreground (lodserver/first_run.py): a test's
# outcome and time must not depend on a background compile another test started.
# tests/test_first_run.py turns the first run's Python mode back on where it tests it.
os.environ["LODSERVER_FIRST_RUN"] = "compile"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]


def need(reason: str):
    """Skip the calling test for a missing browser, tool or service; fail under CI=true."""
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: .ci/run must provide it)", pytrace=False)
    pytest.skip(reason)


@contextmanager
def headless_chromium():
    """A launched headless Chromium (Playwright over Debian's binary), closed after;
    ``need`` without the binary or the playwright package."""
    executable = shutil.which("chromium") or shutil.which("chromium-browser")
    if executable is None:
        need("no chromium binary on PATH (Debian: apt-get install chromium)")
    try:
        from playwright import sync_api
    except ImportError:
        need("the playwright package is not installed")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


def record_calls(monkeypatch, owner, name: str) -> list:
    """Wraps ``owner.name``, a function of one argument, so that each call's argument
    is appended to the returned list before the call runs; the list."""
    calls = []
    original = getattr(owner, name)

    def recorded(argument):
        calls.append(argument)
        return original(argument)

    monkeypatch.setattr(owner, name, recorded)
    return calls


def glb_chunks(data: bytes) -> tuple[dict, bytes]:
    """A GLB's JSON document and binary chunk, asserting its framing: the glTF 2
    header with the file's length, a JSON chunk of a multiple of 4 bytes, then a
    BIN chunk ending the file."""
    magic, version, total = struct.unpack_from("<4sII", data)
    assert (magic, version, total) == (b"glTF", 2, len(data))
    json_length, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON" and json_length % 4 == 0
    document = json.loads(data[20:20 + json_length])
    bin_length, bin_type = struct.unpack_from("<I4s", data, 20 + json_length)
    assert bin_type == b"BIN\x00" and 28 + json_length + bin_length == len(data)
    return document, data[28 + json_length:]


@pytest.fixture
def shared_meshes() -> Path:
    """The shared test meshes beside the repo (../shared/meshes); skips when absent."""
    if not SHARED_MESHES.is_dir():
        pytest.skip(f"shared meshes not found at {SHARED_MESHES}")
    return SHARED_MESHES
