"""lodserver: decimate once, serve every level of detail.

Data flow: ``io.load_mesh`` -> ``quadrics`` -> ``decimate`` -> ``progressive``
-> ``codec`` (the stored ``.pm`` artefact) -> ``store`` -> ``api`` -> ``static/``
(the viewer); ``pipeline`` turns files and folders into LOD chains (GLB).
"""

from .build import build
from .mesh import Mesh, MeshError
from .progressive import Cursor, ProgressiveMesh

__all__ = ["build", "Mesh", "MeshError", "ProgressiveMesh", "Cursor"]
