"""The progressive mesh (Hoppe 1996): the prefix layout and any level directly
(``mesh``), a level moved split by split (``replay``: ``Cursor``), the ``.pm``
artefact it is stored as (``artefact``), and its splits re-ordered into batches
of independent ones (``batches``)."""

from .artefact import ArtefactError
from .batches import Schedule, schedule
from .replay import Cursor
from .mesh import (ProgressiveMesh, decode_progressive, encode_progressive,
                   from_collapse_log, load_progressive, save_progressive)

__all__ = ["ArtefactError", "Cursor", "ProgressiveMesh", "Schedule", "decode_progressive",
           "encode_progressive", "from_collapse_log", "load_progressive", "save_progressive",
           "schedule"]
