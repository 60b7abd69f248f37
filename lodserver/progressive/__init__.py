"""The progressive mesh (Hoppe 1996): the prefix layout, any level directly or by
cursor (``mesh``), and the ``.pm`` artefact it is stored as (``artefact``)."""

from .mesh import Cursor, ProgressiveMesh, from_collapse_log

__all__ = ["Cursor", "ProgressiveMesh", "from_collapse_log"]
