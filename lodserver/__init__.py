"""lodserver: decimate once, serve every level of detail.

Data flow: ``io`` (``load_mesh``) -> ``simplify`` (quadrics, edge collapse,
the collapse log) -> ``progressive`` (``ProgressiveMesh``, the stored ``.pm``
artefact) -> ``packets`` -> ``scene`` (``SceneAsset``: every stored asset, a
scene of parts) -> ``service`` (store, jobs) -> ``api`` -> ``static/`` (the
viewer); ``pipeline`` turns files and folders into LOD chains (GLB), which
levels by ``chains``.
``options.BuildOptions`` holds every build option once, for ``build``, the
command line and the HTTP form alike.
"""

from .numba_cache import ensure_writable_cache

# before any kernel module is imported: numba needs a writable cache folder to decorate one
ensure_writable_cache()


def _version() -> str:
    """The installed distribution's version; in a bare checkout, pyproject.toml's."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("lodserver")
    except PackageNotFoundError:
        import re
        from pathlib import Path

        try:
            text = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
        except OSError:
            return "unknown"
        found = re.search(r'^version\s*=\s*"([^"]+)"', text, re.MULTILINE)
        return found.group(1) if found else "unknown"


__version__ = _version()

from .build import build  # noqa: E402  (after __version__: the CLI imports it from here)
from .mesh import Mesh, MeshError  # noqa: E402
from .options import BuildOptions  # noqa: E402
from .progressive.mesh import ProgressiveMesh
from .progressive.replay import Cursor

__all__ = ["build", "BuildOptions", "Mesh", "MeshError", "ProgressiveMesh", "Cursor",
           "__version__"]
