"""The progressive mesh (Hoppe 1996): the prefix layout, any level directly or by
cursor (``mesh``), and the ``.pm`` artefact it is stored as (``artefact``)."""

from .artefact import ArtefactError
from .mesh import (Cursor, ProgressiveMesh, decode_progressive, encode_progressive,
                   from_collapse_log, load_progressive, save_progressive)

__all__ = ["ArtefactError", "Cursor", "ProgressiveMesh", "decode_progressive",
           "encode_progressive", "from_collapse_log", "load_progressive", "save_progressive"]
