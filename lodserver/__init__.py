"""lodserver: decimate once, serve every level of detail.

Data flow: ``io.load_mesh`` -> ``quadrics`` -> ``decimate`` -> ``progressive``
-> ``codec`` (the stored ``.pm`` artefact).
"""

from .build import build
from .mesh import Mesh, MeshError
from .progressive import Cursor, ProgressiveMesh

__all__ = ["build", "Mesh", "MeshError", "ProgressiveMesh", "Cursor"]
