"""Writing files so that a reader never sees half of one.

Every file lodserver writes (meshes, .pm artefacts, LOD chains, manifests)
goes through :func:`write_atomic`, or :func:`copy_atomic` for a copy of
another file; both write through :func:`atomic_file`.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

# Copies go in pieces of this size (bytes): bounded memory for any file.
CHUNK = 1 << 20


def temporary_beside(path: Path) -> Path:
    """The name a file is written under before it becomes ``path``: beside it (a
    rename is atomic only within one file system) and starting with a dot, so
    that one sweep of ``.*.tmp`` finds every interrupted write."""
    return path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")


@contextlib.contextmanager
def atomic_file(path) -> Iterator[BinaryIO]:
    """A new binary file to write what becomes ``path`` on a clean exit.

    The file is :func:`temporary_beside` ``path``, created with mode 0o666, so
    the process umask gives it the same permissions as any file the process
    creates; nothing touches the process-wide umask, which another thread may
    be relying on. The data is fsynced before ``os.replace``, so a crash leaves
    the old file or the whole new one. On an exception the temporary file is
    removed and ``path`` is untouched.
    """
    path = Path(path)
    temporary = temporary_beside(path)
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def write_atomic(path, data) -> None:
    """Write ``data`` (bytes-like) to ``path`` through :func:`atomic_file`."""
    with atomic_file(path) as file:
        file.write(data)


def copy_atomic(source, dest) -> None:
    """Copy the file ``source`` to ``dest`` through :func:`atomic_file`, in
    pieces of :data:`CHUNK` bytes: ``dest`` is the old file or the whole new one."""
    with open(source, "rb") as reader, atomic_file(dest) as writer:
        shutil.copyfileobj(reader, writer, CHUNK)
