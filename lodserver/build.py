"""One call from a mesh to its progressive mesh: decimate, then renumber."""

from __future__ import annotations

from pathlib import Path

from .decimate import DEFAULT_FLIP_COS, decimate
from .mesh import Mesh, MeshError
from .progressive import ProgressiveMesh, from_collapse_log


def build(source, *, boundary_weight: float = 1.0, locked=None, min_vertices: int = 0,
          flip_cos: float = DEFAULT_FLIP_COS, pair_threshold: float | str = 0.0,
          attribute_weights: dict | None = None, preserve_volume: bool = True,
          progress=None, cancel=None) -> ProgressiveMesh:
    """Build the progressive mesh of ``source``.

    Parameters
    ----------
    source : Mesh or path
        A path is loaded and cleaned with ``io.load_mesh``.
    pair_threshold : float or str
        Distance under which vertices that share no edge may be contracted
        (joining parts): mesh units, or a string like ``"1%"`` for a fraction
        of the bounding-box diagonal. 0 disables it.
    boundary_weight, locked, min_vertices, flip_cos, attribute_weights,
    preserve_volume, progress, cancel
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
    threshold = distance_from(pair_threshold, mesh)
    log = decimate(mesh, boundary_weight=boundary_weight, locked=locked,
                   min_vertices=min_vertices, flip_cos=flip_cos, pair_threshold=threshold,
                   attribute_weights=attribute_weights, preserve_volume=preserve_volume,
                   progress=progress, cancel=cancel)
    metadata["options"] = {
        "boundary_weight": boundary_weight, "min_vertices": min_vertices, "flip_cos": flip_cos,
        "pair_threshold": pair_threshold, "preserve_volume": bool(preserve_volume),
        "attribute_weights": dict(attribute_weights or {}),
        "locked_vertices": 0 if locked is None else int(sum(bool(x) for x in locked))}
    metadata["decimation"] = {"passes": log.passes, "rejected": log.rejected}
    return from_collapse_log(mesh, log, metadata)


def distance_from(value, mesh: Mesh) -> float:
    """A distance in mesh units from a number, or from ``"P%"`` of the bounding-box diagonal."""
    text = str(value).strip()
    try:
        if text.endswith("%"):
            distance = float(text[:-1]) / 100.0 * mesh.bounding_box_diagonal
        else:
            distance = float(text)
    except ValueError:
        raise MeshError(f"a distance must be a number or a percentage like '1%', got {value!r}") from None
    if not distance >= 0 or distance == float("inf"):
        raise MeshError(f"a distance must be finite and non-negative, got {value!r}")
    return distance
