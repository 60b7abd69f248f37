"""The first run on an empty numba cache: a small input's kernels run as Python
while a background process compiles them for the next run.

numba compiles a kernel the first time it is called with a new signature and
keeps the machine code on disk (``cache=True``, ``numba_cache.py``); a later
process loads it at once. On an empty cache, the first ``lodserver build``
of even a 3,000-vertex mesh compiles every kernel it runs (the decimation
kernel and the ~90 functions under it), far longer than the work itself
takes (bench/README.md, "The first run").

What numba allows, and what it does not (numba 0.68):

- it compiles under one lock per process (``global_compiler_lock``): threads
  cannot compile in parallel; only processes can, each writing the on-disk
  cache another then loads;
- the optimisation level (``NUMBA_OPT``) is one setting for the process, read
  when numba is imported; no per-function level but the debugging option
  ``_dbg_optnone``;
- ahead-of-time compilation (``numba.pycc``) is deprecated since 0.57 (still
  importable, with a warning), needs explicit signatures and a C compiler at
  install, and takes no namedtuple or ``parallel=True`` kernels: not an option;
- ``NUMBA_DISABLE_JIT=1`` runs every kernel as its Python function, read once
  at import (for the whole process, not per call). The kernels are plain
  NumPy-on-scalars code: as Python they do the same IEEE float64 operations
  in the same order, and integer arithmetic that wraps stays on NumPy's
  fixed-width scalars, so they write the same artefacts, and for a small
  mesh sooner than compiling them would. A kernel calling a NumPy function
  that numba implements in another order (``np.sum``'s pairwise sums) would
  not: ``tests/test_first_run.py`` holds the artefacts equal, byte for byte,
  on meshes with every kind of attribute.

So on an empty cache, ``lodserver build`` of a file of at most
``SMALL_INPUT_BYTES`` runs itself again in a child process with
``NUMBA_DISABLE_JIT=1`` (:func:`run_as_python`), after starting one
background process (``python -m lodserver.first_run``, lowest priority, in
its own session so it outlives the command) that compiles the kernels an
upload and a build run (``service.warm.warm_up``) into the cache. One lock
file per cache folder keeps a second background compile from starting while
one runs; a larger input waits for a running one (loading what it compiled
rather than compiling it again beside it), and on a cold cache with none
running it compiles as before, with its moving line (``build.CompileTicker``).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

try:
    import fcntl
except ImportError:     # not POSIX: no lock, so no background compile and no Python run
    fcntl = None

__all__ = ["MODE_VARIABLE", "SMALL_INPUT_BYTES", "run_as_python", "should_run_as_python",
           "compiling", "start_background_compile", "wait_for_background_compile", "lock_path"]

# The environment variable that turns the first run's Python mode off
# (``compile``: every build compiles in the foreground, as a test suite or an
# image build wants, to be the same from run to run); any other value, and
# none, keeps it on.
MODE_VARIABLE = "LODSERVER_FIRST_RUN"

# The largest input file (bytes) whose first build runs its kernels as Python:
# about 20,000 vertices of binary PLY, 9,000-15,000 of OBJ, which run as
# Python sooner than the kernels compile (bench/README.md, "The first run").
SMALL_INPUT_BYTES = 1_000_000

_PACKAGE = Path(__file__).resolve().parent


def should_run_as_python(source, method: str = "qem") -> bool:
    """True when this process compiles kernels (numba's JIT is on), the mode is
    not turned off (:data:`MODE_VARIABLE`), ``method``
    is edge collapse (what the tests hold equal as Python), the build's main
    kernel is not in the cache yet or a background compile is filling it, and
    ``source`` is a file of at most ``SMALL_INPUT_BYTES`` (its own size: the
    files it names, such as textures, do not count)."""
    from numba.core import config

    from .build import kernels_cold

    if config.DISABLE_JIT or fcntl is None or method != "qem":
        return False
    if os.environ.get(MODE_VARIABLE, "python").strip().lower() == "compile":
        return False
    try:
        size = Path(source).stat().st_size
    except OSError:
        return False        # the build reports the missing file in its own words
    return size <= SMALL_INPUT_BYTES and (kernels_cold(method) or compiling())


def run_as_python(argv: list[str]) -> int:
    """Start the background compile, then run ``lodserver ARGV`` in a child
    process with numba's JIT off; the child's exit code. Its output goes where
    this process's goes."""
    start_background_compile()
    print("first run: numba has not compiled the kernels yet, so this build runs them as "
          "Python (the same results) while they compile in the background for the next run",
          file=sys.stderr, flush=True)
    # The kernels' hashes wrap around on purpose (compiled, silently); as Python,
    # NumPy's fixed-width scalars wrap the same way but say so each time.
    warnings = "ignore:overflow encountered:RuntimeWarning"
    if os.environ.get("PYTHONWARNINGS"):
        warnings = f"{os.environ['PYTHONWARNINGS']},{warnings}"
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1", "PYTHONWARNINGS": warnings}
    child = subprocess.Popen([sys.executable, "-m", "lodserver.cli", *argv], env=env)
    try:
        return child.wait()
    except KeyboardInterrupt:       # the child got the terminal's SIGINT too
        child.wait()
        return 130


def cache_location() -> str:
    """The folder numba caches this package's kernels in: ``NUMBA_CACHE_DIR`` when
    set (``numba_cache.ensure_writable_cache`` sets it for a read-only package),
    else the package's own ``__pycache__`` folders (named by the package)."""
    return os.environ.get("NUMBA_CACHE_DIR") or str(_PACKAGE)


def lock_path(cache: str | None = None) -> Path:
    """The lock file of the background compile into ``cache`` (default
    :func:`cache_location`), in the temporary folder: one per user and cache.
    While locked it holds the compiling process's id."""
    key = hashlib.sha1(os.path.abspath(cache or cache_location()).encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / f"lodserver-compile-{os.getuid()}-{key}.lock"


def compiling(cache: str | None = None) -> bool:
    """True while a background compile into ``cache`` holds its lock."""
    if fcntl is None:
        return False
    try:
        with _open_lock(lock_path(cache), os.O_RDONLY) as file:    # flock needs no write access
            try:        # shared: two processes asking at once do not see each other as compiling
                fcntl.flock(file, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(file, fcntl.LOCK_UN)
    except OSError:     # no lock file (never compiled in the background here), or no folder
        return False
    return False


def _open_lock(path: Path, flags: int):
    """The lock file opened with ``flags``, never through a symbolic link (the
    temporary folder is everyone's: a link planted there would have the
    compile truncate the file it points at)."""
    return os.fdopen(os.open(path, flags | os.O_NOFOLLOW, 0o600),
                     "r+" if flags & os.O_RDWR else "r")


def start_background_compile() -> subprocess.Popen | None:
    """Start ``python -m lodserver.first_run`` detached (its own session, no
    output), unless one is compiling into the same cache already; the process,
    or None. It takes the lock itself, so two started at once compile once."""
    if compiling():
        return None
    env = {key: value for key, value in os.environ.items() if key != "NUMBA_DISABLE_JIT"}
    try:
        return subprocess.Popen([sys.executable, "-m", "lodserver.first_run"], env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
    except OSError:     # no process to spare: the next run compiles in the foreground
        return None


def wait_for_background_compile(cache: str | None = None, timeout: float | None = None,
                                every: float = 0.5, stream=None) -> bool:
    """Wait until no background compile into ``cache`` holds its lock, polling
    every ``every`` s; False if ``timeout`` s passed first. On a terminal
    ``stream``, a line counting the seconds waited is rewritten at each poll."""
    started = time.monotonic()
    shown = stream is not None and getattr(stream, "isatty", lambda: False)()
    while compiling(cache):
        waited = time.monotonic() - started
        if timeout is not None and waited > timeout:
            return False
        if shown:
            stream.write(f"\rwaiting for the kernels compiling in the background: {waited:.0f} s")
            stream.flush()
        time.sleep(every)
    if shown and time.monotonic() - started > every:
        stream.write("\n")
        stream.flush()
    return True


def _compile_in_background() -> int:
    """The background process: under the lock, at the lowest priority, load or
    compile every kernel an upload's build and its packets run
    (``service.warm.warm_up``). Exits at once when another holds the lock."""
    try:
        file = _open_lock(lock_path(), os.O_RDWR | os.O_CREAT)
    except OSError:
        return 1
    with file:
        if not _take(file):
            return 0
        file.truncate(0)
        file.write(f"{os.getpid()}\n")      # who holds it, for whoever wonders
        file.flush()
        try:
            os.nice(19)     # the foreground build, and whatever else runs, come first
        except OSError:
            pass
        from .service.warm import warm_up

        warm_up()
    return 0


def _take(file, patience: float = 2.0) -> bool:
    """Take the lock of ``file``, trying again for ``patience`` s: a process asking
    whether a compile runs (:func:`compiling`) holds it for an instant, a compile
    for as long as it compiles. False when another compile holds it."""
    deadline = time.monotonic() + patience
    while True:
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)


if __name__ == "__main__":
    sys.exit(_compile_in_background())
