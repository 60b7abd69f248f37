"""The peer simplifiers, each behind one call: numpy in, numpy out.

Every function takes welded ``positions`` (n, 3) float64, ``faces`` (m, 3)
int64 and a target triangle count, and returns ``(positions, faces)`` as
numpy arrays. Any conversion a caller of the library would have to do
(dtypes, flattening, building a MeshSet) happens inside, so it is timed.

The settings follow ``/work/shared/PEERS.md`` ("as a careful user would
choose them"). Each library is imported on first use, so a worker process
only loads the library it measures.
"""

from __future__ import annotations

import numpy as np

# meshoptimizer: the target triangle count decides, not the error bound.
MESHOPT_TARGET_ERROR = 1.0
MESHOPT_OPTIONS = 0

# pymeshlab 2025.7: an omitted parameter silently keeps its value from the
# previous call in the same process, so every parameter is given, the ones
# not named in PEERS.md at the filter's documented default.
PYMESHLAB_SETTINGS = {
    "targetperc": 0.0,
    "qualitythr": 0.3,
    "preserveboundary": False,
    "boundaryweight": 1.0,
    "preservenormal": True,
    "preservetopology": False,
    "optimalplacement": True,
    "planarquadric": False,
    "planarweight": 0.001,
    "qualityweight": False,
    "autoclean": True,
    "selected": False,
}

FAST_SIMPLIFICATION_AGG = 7.0


def _meshoptimizer(simplify, positions, faces, target, **options):
    """One of meshoptimizer's simplifiers, ``simplify``, down to ``target`` triangles."""
    # The wrapper wants a flat uint32 index buffer and float32 positions.
    indices = np.ascontiguousarray(faces, dtype=np.uint32).ravel()
    destination = np.empty_like(indices)
    count = simplify(
        destination,
        indices,
        np.ascontiguousarray(positions, dtype=np.float32),
        target_index_count=3 * target,
        target_error=MESHOPT_TARGET_ERROR,
        **options,
    )
    # Output indices refer to the input vertices, which it never moves.
    return positions, destination[:count].reshape(-1, 3).astype(np.int64)


def meshoptimizer_simplify(positions, faces, target):
    """``meshopt_simplify`` (edge collapse that keeps original vertices)."""
    import meshoptimizer

    return _meshoptimizer(meshoptimizer.simplify, positions, faces, target,
                          options=MESHOPT_OPTIONS)


def meshoptimizer_sloppy(positions, faces, target):
    """``meshopt_simplifySloppy`` (vertex clustering, topology not kept)."""
    import meshoptimizer

    return _meshoptimizer(meshoptimizer.simplify_sloppy, positions, faces, target)


def pymeshlab_simplify(positions, faces, target):
    """MeshLab's quadric edge collapse, on a fresh MeshSet."""
    import pymeshlab

    meshset = pymeshlab.MeshSet()
    meshset.add_mesh(
        pymeshlab.Mesh(vertex_matrix=positions, face_matrix=faces.astype(np.int32))
    )
    meshset.meshing_decimation_quadric_edge_collapse(
        targetfacenum=int(target), **PYMESHLAB_SETTINGS
    )
    result = meshset.current_mesh()
    return result.vertex_matrix(), result.face_matrix().astype(np.int64)


def fast_simplification_simplify(positions, faces, target):
    """fast-simplification (Fast-Quadric-Mesh-Simplification, no heap)."""
    import fast_simplification

    # 0.2.0 takes target_count directly (PEERS.md's setting), so no reduction
    # fraction has to be derived from it.
    points, triangles = fast_simplification.simplify(
        positions,
        faces,
        target_count=int(target),
        agg=FAST_SIMPLIFICATION_AGG,
        verbose=False,
        return_collapses=False,
        lossless=False,
        preserve_border=False,
    )
    return points, triangles.astype(np.int64)


PEERS = {
    "meshoptimizer": meshoptimizer_simplify,
    "meshoptimizer-sloppy": meshoptimizer_sloppy,
    "pymeshlab": pymeshlab_simplify,
    "fast-simplification": fast_simplification_simplify,
}

# The same settings, JSON-able, for the results file.
PEER_SETTINGS = {
    "meshoptimizer": {
        "call": "simplify",
        "target_index_count": "3N",
        "target_error": MESHOPT_TARGET_ERROR,
        "options": MESHOPT_OPTIONS,
    },
    "meshoptimizer-sloppy": {
        "call": "simplify_sloppy",
        "target_index_count": "3N",
        "target_error": MESHOPT_TARGET_ERROR,
    },
    "pymeshlab": {
        "call": "meshing_decimation_quadric_edge_collapse",
        "targetfacenum": "N",
        **PYMESHLAB_SETTINGS,
    },
    "fast-simplification": {
        "call": "simplify",
        "target_count": "N",
        "agg": FAST_SIMPLIFICATION_AGG,
        "lossless": False,
        "preserve_border": False,
    },
}
