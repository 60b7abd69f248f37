"""numba's cache when every folder it would use is read-only, as in ``docker run
--read-only``: the package, HOME and ``NUMBA_CACHE_DIR`` are bind-mounted
read-only in a mount namespace of their own (``unshare -m``, root), the temporary
directory stays writable (``--tmpfs /tmp``). lodserver imports, compiles into a
private folder there, still loads the kernels the read-only cache holds, and
``lodserver serve`` starts and is ready."""

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from .server import _free_port

PACKAGE = Path(__file__).resolve().parents[1] / "lodserver"
# A cheap compiled kernel: its cache files are named after it.
CALL_TAKE_ROWS = ("import numpy as np; from lodserver.mesh import _take_rows as take_rows; "
                  "take_rows(np.zeros((3, 2)), np.array([0, 2])); "
                  "print(sum(take_rows.stats.cache_hits.values()), "
                  "sum(take_rows.stats.cache_misses.values()))")
# The mounts, then the command: the package, HOME and the cache read-only.
MOUNTS = ('for folder in "$PACKAGE" "$HOME" "$NUMBA_CACHE_DIR"; do '
          'mount --bind -o ro "$folder" "$folder" || exit 97; done; cd / && exec "$@"')


@pytest.fixture
def read_only(tmp_path):
    """A function running a command with the package, HOME and NUMBA_CACHE_DIR
    (tmp_path/cache) read-only and TMPDIR tmp_path/tmp writable; a Popen."""
    if shutil.which("unshare") is None or os.geteuid() != 0:
        pytest.skip("read-only mounts need root and unshare(1); "
                    "lodserver/numba_cache.py's rule is checked by them only")
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True)
    if probe.returncode:
        pytest.skip(f"cannot make a mount namespace here: {probe.stderr.decode().strip()}")
    for name in ("cache", "home", "tmp"):
        (tmp_path / name).mkdir()

    def run(*command, env=None, **popen):
        env = {**os.environ, "PACKAGE": str(PACKAGE), "HOME": str(tmp_path / "home"),
               "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "TMPDIR": str(tmp_path / "tmp"),
               "PYTHONPATH": str(PACKAGE.parent), "XDG_CACHE_HOME": "", **(env or {})}
        return subprocess.Popen(["unshare", "-m", "sh", "-c", MOUNTS, "sh", *command],
                                env=env, **popen)
    return run


def _finish(process) -> str:
    out, _ = process.communicate(timeout=600)
    assert process.returncode == 0, out
    return out


def test_kernels_compile_into_a_private_folder_when_every_cache_folder_is_read_only(
        read_only, tmp_path):
    out = _finish(read_only(sys.executable, "-c", "import os; " + CALL_TAKE_ROWS +
                            "; print(os.environ['NUMBA_CACHE_DIR'])",
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    hits, misses, folder = out.split()[-3:]
    assert (hits, misses) == ("0", "1")
    folder = Path(folder)
    assert folder == tmp_path / "tmp" / f"lodserver-numba-{os.getuid()}"
    assert folder.stat().st_mode & 0o777 == 0o700
    saved = list(folder.rglob("mesh._take_rows-*.nbi"))
    assert len(saved) == 1 and not saved[0].is_symlink()
    assert list((tmp_path / "cache").iterdir()) == []


def test_the_kernels_of_a_read_only_cache_are_loaded_not_compiled_again(read_only, tmp_path):
    # the image's build: kernels compiled into NUMBA_CACHE_DIR while it is writable
    done = subprocess.run([sys.executable, "-c", CALL_TAKE_ROWS], capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(PACKAGE.parent),
                                          "NUMBA_CACHE_DIR": str(tmp_path / "cache")})
    assert done.returncode == 0 and done.stdout.split() == ["0", "1"], done.stderr
    before = {path: path.stat().st_mtime_ns for path in (tmp_path / "cache").rglob("*")}
    out = _finish(read_only(sys.executable, "-c", CALL_TAKE_ROWS, stdout=subprocess.PIPE,
                            text=True))
    assert out.split() == ["1", "0"]            # a cache hit, nothing compiled
    index = list((tmp_path / "tmp").rglob("mesh._take_rows-*.nbi"))
    assert len(index) == 1 and index[0].is_symlink()
    assert {path: path.stat().st_mtime_ns
            for path in (tmp_path / "cache").rglob("*")} == before


def test_serve_starts_and_is_ready_with_every_cache_folder_read_only(read_only, tmp_path):
    port = _free_port()
    server = read_only(sys.executable, "-m", "lodserver.cli", "serve",
                       "--data", str(tmp_path / "data"), "--port", str(port),
                       "--log-level", "warning", env={"LODSERVER_WARM_KERNELS": "false"},
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                response = httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=5)
                if response.status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert server.poll() is None, server.stdout.read()
            assert time.monotonic() < deadline, "the server did not become ready"
            time.sleep(0.2)
        assert response.json() == {"status": "ok", "ready": True}
    finally:
        server.terminate()
        server.wait(30)
    assert (tmp_path / "tmp" / f"lodserver-numba-{os.getuid()}").is_dir()
