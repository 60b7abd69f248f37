"""One call from a mesh to its progressive mesh: decimate (or octree-cluster), then renumber."""

from __future__ import annotations

from pathlib import Path

from .decimate import DEFAULT_FLIP_COS, decimate
from .mesh import Mesh, MeshError
from .progressive import ProgressiveMesh, from_collapse_log

METHODS = ("qem", "cluster")


def build(source, *, method: str = "qem", boundary_weight: float = 1.0, locked=None,
          min_vertices: int = 0,
          flip_cos: float = DEFAULT_FLIP_COS, pair_threshold: float | str = 0.0,
          attribute_weights: dict | None = None, preserve_volume: bool = True,
          attributes: bool = True, seam_weight: float = 1.0, progress=None,
          cancel=None) -> ProgressiveMesh:
    """Build the progressive mesh of ``source``.

    Parameters
    ----------
    source : Mesh or path
        A path is loaded and cleaned with ``io.load_mesh``.
    method : str
        ``"qem"``: quadric edge collapse (``decimate``), manifold-preserving,
        with attributes. ``"cluster"``: octree vertex clustering recorded as
        collapses (``octree``): faster on huge inputs, joins parts, geometry
        only; the options below other than ``attributes`` do not apply to it.
    pair_threshold : float or str
        Distance under which vertices that share no edge may be contracted
        (joining parts): mesh units, or a string like ``"1%"`` for a fraction
        of the bounding-box diagonal. 0 disables it.
    attributes : bool
        Simplify the mesh's normals, UVs and colours with it (default); False
        builds from positions and faces alone (materials dropped too).
    boundary_weight, locked, min_vertices, flip_cos, attribute_weights,
    preserve_volume, seam_weight, progress, cancel
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
    if method not in METHODS:
        raise MeshError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if not attributes or method == "cluster":
        mesh = Mesh(mesh.positions, mesh.faces)
    if method == "cluster":
        from .octree import octree_log
        log = octree_log(mesh)
        metadata["options"] = {"method": method}
        metadata["decimation"] = {"passes": log.passes}
        return from_collapse_log(mesh, log, metadata)
    threshold = distance_from(pair_threshold, mesh)
    log = decimate(mesh, boundary_weight=boundary_weight, locked=locked,
                   min_vertices=min_vertices, flip_cos=flip_cos, pair_threshold=threshold,
                   attribute_weights=attribute_weights, preserve_volume=preserve_volume,
                   seam_weight=seam_weight, progress=progress, cancel=cancel)
    metadata["options"] = {
        "method": method, "boundary_weight": boundary_weight, "min_vertices": min_vertices, "flip_cos": flip_cos,
        "pair_threshold": pair_threshold, "preserve_volume": bool(preserve_volume),
        "seam_weight": seam_weight,
        "attributes": [name for name, _ in mesh.attributes.layout] if mesh.attributes else [],
        "attribute_weights": dict(attribute_weights or {}),
        "locked_vertices": 0 if locked is None else int(sum(bool(x) for x in locked))}
    metadata["decimation"] = {"passes": log.passes, "rejected": log.rejected}
    return from_collapse_log(mesh, log, metadata)


def attribute_weights(*, normal=None, uv=None, color=None) -> dict:
    """``build``'s attribute_weights from per-kind weights; None keeps the default."""
    weights = {}
    if normal is not None:
        weights["NORMAL"] = normal
    if uv is not None:
        weights["TEXCOORD_0"] = weights["TEXCOORD_1"] = uv
    if color is not None:
        weights["COLOR_0"] = color
    return weights


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
