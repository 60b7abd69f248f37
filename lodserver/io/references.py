"""The one rule for files a mesh file names, and a reader that reads no more than allowed.

A ``.gltf`` names its buffers and images by URI, an OBJ its ``mtllib``
libraries, an MTL its texture maps. For an upload those names are chosen by
whoever sent the file, so with a ``root`` folder (the upload's) every name
must resolve, after URL-unquoting (glTF only) and normalising, to a regular
file inside ``root``. Refused, always naming the reference *as written* and
never a server path:

- any scheme but ``data:`` (``file:``, ``http:``, ``https:``, ...): never fetched;
- with ``root``: absolute paths, ``..`` that leaves ``root``, a symlink in any
  component below ``root``;
- device files, fifos, sockets, directories, and anything under ``/proc``,
  ``/sys`` or ``/dev`` (whose "regular" files report size 0 and then stream).

Without ``root`` (the command line, reading its user's own files) a name is
taken relative to the referring file, symlinks and ``..`` included.

The file is opened with ``O_NONBLOCK`` (a fifo must not hang the reader) and
checked again on the open descriptor, and only the bytes its size promised
are read, never more than the caller's limit.

A ``root`` may be filled on demand (:func:`extract_on_demand`, a set's archive
in :mod:`.fileset`): each name is offered to its extractor, after the checks
above and before the file is looked for, so only the files a mesh names are
ever written.
"""

from __future__ import annotations

import os
import re
import stat
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path, PurePosixPath
from urllib.parse import unquote

from ..mesh import MeshError
from .limits import LimitError

# RFC 3986 scheme; one letter is a Windows drive ("C:/..."), handled as a path.
_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.\-]+):")
_PSEUDO_FILE_SYSTEMS = ("/proc", "/sys", "/dev")


class MissingReferenceError(MeshError):
    """A referenced file does not exist (an OBJ's missing ``mtllib`` is only reported)."""


# (real path of a root, its extractor) while a load fills that root on demand
_ON_DEMAND: ContextVar[tuple[str, object] | None] = ContextVar("on_demand", default=None)


@contextmanager
def extract_on_demand(root, extract):
    """While the block runs, a name resolved inside ``root`` is first passed to
    ``extract(parts)`` (its normalised components below ``root``, a list of str),
    which writes that file into ``root`` if it has one of that name and returns;
    the name is then looked for as usual."""
    token = _ON_DEMAND.set((os.path.realpath(root), extract))
    try:
        yield
    finally:
        _ON_DEMAND.reset(token)


def resolve_reference(uri: str, folder: Path, root: Path | None, what: str, *,
                      url: bool = True) -> Path:
    """The file a reference names, checked by the rules of this module.

    Parameters
    ----------
    uri : str
        The reference as written in the file (a glTF URI, an OBJ/MTL file name).
    folder : Path
        The folder of the referring file; relative names start there.
    root : Path or None
        The folder every reference must stay inside (symlinks refused), or None
        for the trusted rule.
    what : str
        What the reference is, for messages (``"buffer 0"``, ``"texture"``).
    url : bool
        Whether ``uri`` is a URI (%-escapes decoded, as glTF), or a plain file
        name (OBJ, MTL), where ``%`` is a character like any other.

    Returns
    -------
    Path
        The normalised path to read (inside ``root`` when it is given).

    Raises
    ------
    MeshError
        Naming ``what`` and ``uri``: a scheme, an absolute path or an escape
        from ``root``, a symlink, a non-regular file.
    MissingReferenceError
        When no file of that name exists.
    """
    scheme = _SCHEME.match(uri)
    if scheme:
        raise MeshError(f"its {what} {uri!r} is a {scheme.group(1).lower()}: URI; "
                        "only files beside it and data: URIs are read")
    name = (unquote(uri) if url else uri).replace("\\", "/")
    if "\0" in name:
        raise MeshError(f"its {what} {uri!r} contains a NUL character")
    if root is None:
        file = folder / name
        _check_not_pseudo(file, uri, what)
        return file
    pure = PurePosixPath(name)
    if pure.is_absolute() or re.match(r"^[A-Za-z]:", name):
        raise MeshError(f"its {what} {uri!r} is an absolute path; only files beside it are read")
    root = Path(os.path.realpath(root))
    here = Path(os.path.realpath(folder))
    try:
        parts = list(here.relative_to(root).parts)
    except ValueError:
        raise MeshError(f"its {what} {uri!r} is referred to from outside the upload") from None
    for part in pure.parts:
        if part in ("", "."):
            continue
        if part == "..":
            if not parts:
                raise MeshError(f"its {what} {uri!r} leads out of the folder it was uploaded in")
            parts.pop()
        else:
            parts.append(part)
    demand = _ON_DEMAND.get()
    if demand is not None and demand[0] == str(root) and parts:
        demand[1](parts)
    # every component below root must be a real directory (or, last, a regular file)
    file = root
    for at, part in enumerate(parts):
        file = file / part
        try:
            mode = os.lstat(file).st_mode
        except FileNotFoundError:
            raise MissingReferenceError(f"its {what} file {uri!r} is missing") from None
        except OSError as exc:
            raise MeshError(f"its {what} {uri!r} cannot be read ({exc.strerror})") from None
        if stat.S_ISLNK(mode):
            raise MeshError(f"its {what} {uri!r} goes through a symbolic link, which is not "
                            "followed in an upload")
        if at < len(parts) - 1 and not stat.S_ISDIR(mode):
            raise MissingReferenceError(f"its {what} file {uri!r} is missing")
    if not parts:
        raise MeshError(f"its {what} {uri!r} names a folder, not a file")
    return file


def _check_not_pseudo(file: Path, uri: str, what: str) -> None:
    """Refuse names that resolve into /proc, /sys or /dev."""
    real = os.path.realpath(file)
    if any(real == top or real.startswith(top + "/") for top in _PSEUDO_FILE_SYSTEMS):
        raise MeshError(f"its {what} {uri!r} is not a regular file")


def read_reference(file: Path, uri: str, what: str, *, limit: int | None,
                   length: int | None = None, follow: bool = True) -> bytes:
    """The bytes of a referenced (already resolved) file, bounded.

    Parameters
    ----------
    file : Path
        From :func:`resolve_reference`.
    uri, what : str
        The reference as written and what it is, for messages.
    limit : int or None
        Most bytes the file may have (``LoadLimits.max_file_bytes``); a larger
        file is refused before a byte is read.
    length : int, optional
        Read only the first ``length`` bytes (a glTF buffer's ``byteLength``);
        refused if the file is shorter.
    follow : bool
        False refuses a symlink as the last component (``O_NOFOLLOW``), for
        references confined to a root.

    Raises
    ------
    MeshError, MissingReferenceError, LimitError
    """
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    if not follow:
        flags |= getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(file, flags)
    except FileNotFoundError:
        raise MissingReferenceError(f"its {what} file {uri!r} is missing") from None
    except OSError as exc:
        raise MeshError(f"its {what} {uri!r} cannot be read ({exc.strerror})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise MeshError(f"its {what} {uri!r} is not a regular file")
        size = info.st_size
        if length is not None:
            if size < length:
                raise MeshError(f"its {what} file {uri!r} holds {size} bytes, fewer than the "
                                f"{length} it should have")
            size = length
        if limit is not None and size > limit:
            raise LimitError(f"its {what} file {uri!r} has {size} bytes; this loader reads at "
                             f"most {limit} from one file")
        chunks, left = [], size
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 24))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
        data = b"".join(chunks)
    finally:
        os.close(fd)
    if len(data) < size:
        raise MeshError(f"its {what} file {uri!r} ended before its stated size")
    return data
