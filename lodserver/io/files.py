"""Writing files so that a reader never sees half of one.

Every file lodserver writes (meshes, .pm artefacts, LOD chains, manifests)
goes through :func:`write_atomic`.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path


def write_atomic(path, data) -> None:
    """Write ``data`` (bytes-like) to ``path`` through a temporary file and a rename.

    The temporary file is created next to ``path`` (a rename is atomic only
    within one file system) with mode 0o666, so the process umask gives it the
    same permissions as any file the process creates; nothing touches the
    process-wide umask, which another thread may be relying on. The data is
    fsynced before ``os.replace``, so a crash leaves the old file or the whole
    new one. On failure the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as file:
            file.write(data)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
