"""One call from a mesh to its progressive mesh: decimate (or octree-cluster), then renumber."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
from numba.core import event as numba_event

from .simplify.carried import complete_log, solved_part
from .simplify.collapse import decimate
from .mesh import Mesh, MeshError
from .options import METHODS, BuildOptions, distance_from
from .progressive.batches import schedule
from .progressive.mesh import ProgressiveMesh, from_collapse_log

__all__ = ["build", "BuildOptions", "METHODS", "distance_from", "kernels_cold", "CompileTicker"]

# About what the first build on a small machine spends compiling the kernels
# numba has not cached yet (an empty NUMBA_CACHE_DIR): told to the user so the
# first run does not look hung.
COLD_COMPILE_SECONDS = 40


def build(source, options: BuildOptions | dict | None = None, *, locked=None, progress=None,
          cancel=None, untrusted: bool = False, poses=None, **overrides) -> ProgressiveMesh:
    """Build the progressive mesh of ``source``.

    Parameters
    ----------
    source : Mesh or path
        A path is loaded and cleaned with ``io.load_mesh``.
    options : BuildOptions or dict, optional
        The build options (``options.BuildOptions``: method, weights, pair
        threshold, ...); None takes every default. Keywords override single
        options: ``build(mesh, boundary_weight=2)``.
    locked : (n,) bool, optional
        Vertices that must neither move nor vanish (``lock_border`` adds the
        border vertices to them).
    progress : callable(done: int, expected: int), optional
        Called about ten times a second while the kernel runs.
    cancel : threading.Event, optional
        When set, decimation stops at the next progress check.
    untrusted : bool
        ``source`` is a file from someone else: load it as the server loads an
        upload (every file it names must lie in its folder, no symlinks or URLs,
        the default ``LoadLimits``).
    poses : (P, n, 3, 4) float64, optional
        Per pose, every vertex's affine map from bind to posed position
        (``simplify.poses.scene_poses``): a skinned or morphed mesh's error is then
        measured in those poses too (``simplify.collapse.decimate``).

    Returns
    -------
    ProgressiveMesh
        Its full level equals the (cleaned) input exactly.

    Raises
    ------
    MeshError
        An option is out of range or malformed (one sentence naming it), or the
        mesh cannot be used. TypeError for a keyword that is not a build option.
    """
    options = BuildOptions.check(options, **overrides)
    metadata = {}
    if isinstance(source, Mesh):
        mesh = source
    else:
        from .io import load_mesh
        if Path(source).is_dir():
            raise MeshError(f"{source} is a folder; pass a mesh file")
        mesh, report = load_mesh(source, root=Path(source).parent if untrusted else None)
        metadata["source"] = Path(source).name
        metadata["load_report"] = report.as_dict()
    if not options.attributes or options.method == "cluster":
        mesh = Mesh(mesh.positions, mesh.faces)
    if options.method == "cluster":
        from .simplify.octree import octree_log
        log = octree_log(mesh)
        metadata["options"] = {"method": options.method}
        metadata["decimation"] = {"passes": log.passes}
        pm = from_collapse_log(mesh, log, metadata)
        return schedule(pm).pm if options.batched else pm
    locked = _locked(mesh, locked, options.lock_border)
    kernel = options.decimate_options(mesh)
    # the kernel ranks on the solved attributes; the carried ones follow the log
    log = decimate(solved_part(mesh), kernel, locked=locked, poses=poses, progress=progress,
                   cancel=cancel)
    log = complete_log(mesh, log)
    metadata["options"] = {
        **options.recorded(),
        "attributes": [name for name, _ in mesh.attributes.layout] if mesh.attributes else [],
        "attribute_weights": dict(kernel.attribute_weights),
        "locked_vertices": 0 if locked is None else int(np.count_nonzero(locked))}
    metadata["decimation"] = {"passes": log.passes, "rejected": log.rejected}
    pm = from_collapse_log(mesh, log, metadata)
    return schedule(pm).pm if options.batched else pm


def _locked(mesh: Mesh, locked, lock_border: bool):
    """(n,) bool or None: ``locked`` with the border vertices added if ``lock_border``."""
    if not lock_border:
        return locked
    from .simplify.topology import census
    mask = np.zeros(mesh.vertex_count, dtype=bool)
    if locked is not None:
        mask |= np.asarray(locked, dtype=bool)
    mask[census(mesh.faces, mesh.vertex_count).on_boundary] = True
    return mask


def kernels_cold(method: str = "qem") -> bool:
    """True if numba has no usable on-disk cache of ``method``'s main kernel yet,
    so the next build spends ``COLD_COMPILE_SECONDS`` or so compiling it.

    Reads the kernel's cache index where numba's own locator puts it
    (``__pycache__`` beside the module, or ``NUMBA_CACHE_DIR``); an index made
    for an older copy of the source counts as cold, as numba treats it. Answers
    False when caching is off or numba's layout is not the expected one (then
    nothing is announced; the build itself is the same either way).
    """
    try:
        if method == "cluster":
            from .simplify.octree import MAIN_KERNEL as kernel
        else:
            from .simplify.collapse import MAIN_KERNEL as kernel
        cache = kernel._cache
        if not hasattr(cache, "_cache_file"):
            return False        # cache=False: compiled every run, nothing to announce
        return not cache._cache_file._load_index()
    except Exception:       # the kernel or numba's internals moved: say nothing, build on
        return False


class CompileTicker:
    """A line on ``stream`` that moves while numba compiles: the kernel being
    compiled, how many are done and the seconds so far, rewritten in place
    every ``every`` s from a thread of its own (a kernel can take seconds to
    compile, and a line that sits still looks hung). Nothing is written while
    nothing compiles (a filled cache), nor when ``stream`` is not a terminal
    unless ``always``. ``stop()`` ends the line.

    It listens to numba's compile events (``numba.core.event``), which numba
    sends from the compiling thread for each kernel, nested ones included.
    """

    def __init__(self, stream=None, every: float = 0.25, always: bool = False):
        self.stream = sys.stderr if stream is None else stream
        self.every = every
        self.enabled = always or getattr(self.stream, "isatty", lambda: False)()
        self.compiling: list[str] = []      # names of the kernels being compiled, outermost first
        self.done = 0
        self.started: float | None = None
        self.shown = False
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._listener = _CompileListener(self)
        if self.enabled:
            numba_event.register("numba:compile", self._listener)
            self._thread = threading.Thread(target=self._run, name="compile-ticker", daemon=True)
            self._thread.start()

    def line(self) -> str:
        """What the line says now."""
        with self._lock:
            current = self.compiling[-1] if self.compiling else "done"
            elapsed = time.monotonic() - (self.started or time.monotonic())
            return (f"compiling kernels (first run only): {self.done} compiled, "
                    f"{elapsed:.0f} s, now {current}")

    def _run(self) -> None:
        while not self._stop.wait(self.every):
            if self.compiling:      # quiet between compiles: a progress bar may be showing
                self._write()

    def _write(self) -> None:
        self.stream.write("\r" + self.line().ljust(100)[:100])
        self.stream.flush()
        self.shown = True

    def stop(self) -> None:
        """Stop listening; finish the line if one was shown."""
        if not self.enabled or self._stop.is_set():
            return
        self._stop.set()
        self._thread.join()
        numba_event.unregister("numba:compile", self._listener)
        if self.shown:
            self._write()
            self.stream.write("\n")
            self.stream.flush()


class _CompileListener(numba_event.Listener):
    """numba's compile events into a ``CompileTicker``'s counts."""

    def __init__(self, ticker: CompileTicker):
        self.ticker = ticker

    def on_start(self, event) -> None:
        function = getattr(event.data.get("dispatcher"), "py_func", None)
        ticker = self.ticker
        with ticker._lock:
            if ticker.started is None:
                ticker.started = time.monotonic()
            ticker.compiling.append(getattr(function, "__name__", "kernel"))

    def on_end(self, event) -> None:
        ticker = self.ticker
        with ticker._lock:
            if ticker.compiling:
                ticker.compiling.pop()
            ticker.done += 1
