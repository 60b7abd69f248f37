"""One call from a mesh to its progressive mesh: decimate, then renumber."""

from __future__ import annotations

from pathlib import Path

from .decimate import DEFAULT_FLIP_COS, decimate
from .mesh import Mesh
from .progressive import ProgressiveMesh, from_collapse_log


def build(source, *, boundary_weight: float = 1.0, locked=None, min_vertices: int = 0,
          flip_cos: float = DEFAULT_FLIP_COS, progress=None, cancel=None) -> ProgressiveMesh:
    """Build the progressive mesh of ``source``.

    Parameters
    ----------
    source : Mesh or path
        A path is loaded and cleaned with ``io.load_mesh``.
    boundary_weight, locked, min_vertices, flip_cos, progress, cancel
        See ``decimate.decimate``.

    Returns
    -------
    ProgressiveMesh
        Its full level equals the (cleaned) input exactly.
    """
    metadata = {}
    if isinstance(source, Mesh):
        mesh = source
    else:
        from .io import load_mesh
        mesh, report = load_mesh(source)
        metadata["source"] = Path(source).name
        metadata["load_report"] = report.as_dict()
    log = decimate(mesh, boundary_weight=boundary_weight, locked=locked,
                   min_vertices=min_vertices, flip_cos=flip_cos, progress=progress, cancel=cancel)
    metadata["options"] = {"boundary_weight": boundary_weight, "min_vertices": min_vertices,
                           "flip_cos": flip_cos, "locked_vertices": 0 if locked is None
                           else int(sum(bool(x) for x in locked))}
    metadata["decimation"] = {"passes": log.passes, "rejected": log.rejected}
    return from_collapse_log(mesh, log, metadata)
