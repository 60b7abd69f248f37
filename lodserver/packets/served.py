"""The packet versions the server writes, one table: version -> the function that
cuts the packet ``A -> B`` of a progressive mesh from its cached records.

``GET /meshes/{id}/splits?version=K`` looks its writer up here and a mesh's
summary lists the keys (``packet_versions``), so that a client picks the newest
it reads. Version 3 stays the default: clients written before version 4 ask
without ``version`` and must keep getting what they read.
"""

from __future__ import annotations

from .records import packet_between
from .records_v4 import packet_between_v4

# version -> writer(pm, start, stop, *, bits=None) -> bytes
PACKET_WRITERS = {3: packet_between, 4: packet_between_v4}
SERVED_VERSIONS = tuple(sorted(PACKET_WRITERS))
DEFAULT_VERSION = 3
