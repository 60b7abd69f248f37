"""An upload of several files: the names, the main mesh file, and the one archive that keeps them.

A mesh often comes as a set: an OBJ with its ``.mtl`` and textures, a
``.gltf`` with its ``.bin`` and images. Such a set arrives as several form
parts or as one ``.zip``, from someone else, so everything here assumes the
names and the archive are hostile:

- every name a client gives that is kept (a file's, the ``name`` field) passes
  :func:`check_name`: no control character (C0, DEL, C1), at most
  :data:`MAX_NAME_BYTES` in UTF-8, so every catalogue stores it as it is;
- a part's name is reduced to its base name and must be a plain one
  (:func:`plain_name`): no folder, no ``..``, no leading dot, no control
  characters; two parts may not share a name; a set has at most
  ``FileSetLimits.max_files`` files;
- a zip is checked whole before a byte is extracted (:func:`unpack_zip`): the
  count its end record declares, then every entry's name (relative, no
  ``..``, no drive, sub-folders at most ``max_depth`` deep, no duplicates), its
  kind (regular files and folders only: no symlinks, devices or encrypted
  entries), the total of the sizes it declares and its compression ratio (a
  zip bomb declares gigabytes in kilobytes). Extraction then writes each file
  with ``O_EXCL | O_NOFOLLOW`` into folders it made itself, and zipfile stops
  every entry at its declared size (and checks its CRC), so what is written is
  what was checked.

The set is kept as one archive, so the catalogue keeps one source file per
mesh: a zip as it was uploaded, still compressed, once :func:`list_zip` has
checked it whole without extracting a byte (so it is unpacked only where it is
parsed), with the main file's name written into its comment
(:func:`name_main`); files sent as form parts packed into a new one
(:func:`pack_set`, stored uncompressed). :func:`open_set` checks that archive
by the same rules and extracts its main file into a folder of its own, which
is then loaded with ``root=`` that folder: references resolve only inside the
set, and each file is extracted only when a reference names it, so the files
of a set that the mesh never names are never written.

Every error is a :class:`~lodserver.mesh.MeshError` of one sentence naming
entries as the client wrote them, never a server path.
"""

from __future__ import annotations

import os
import re
import shutil
import stat
import struct
import zipfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from ..mesh import MeshError
from .limits import LimitError
from .load import SUPPORTED_INPUT
from .references import extract_on_demand

__all__ = ["DEFAULT_SET_LIMITS", "MAX_NAME_BYTES", "FileSetLimits", "NoMeshFile", "check_name",
           "list_zip", "load_warnings", "name_main", "open_set", "pack_set", "pick_main",
           "plain_name", "unpack_zip"]

# Entries smaller than this are not held to the ratio limit: a short, repetitive
# text (an MTL, a small OBJ) legitimately compresses by a lot, and cannot be a bomb.
RATIO_FREE_BYTES = 1 << 20
# The comment of an archive written by pack_set: this prefix, then the main file's name.
_MAIN_TAG = b"lodserver-main:"
# Junk that archivers add (macOS resource forks), skipped rather than refused.
_JUNK_FOLDERS = ("__MACOSX",)
# Control characters: C0 (NUL among them, which PostgreSQL cannot store in text),
# DEL and C1. None belongs in a name, and they hide what a name says in logs and pages.
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")
# UTF-8 bytes of a name a client gives (a file's or a mesh's): what most file
# systems allow in one component.
MAX_NAME_BYTES = 255


class NoMeshFile(MeshError):
    """The set holds no file of a type lodserver reads (an upload answers 415)."""


@dataclass(frozen=True)
class FileSetLimits:
    """Bounds on a set of uploaded files.

    max_files : int
        Form parts of one upload (files, not fields).
    max_entries : int
        Entries of a zip, folders included.
    max_unpacked_bytes : int
        Sum of the sizes a zip's files declare, in bytes (what extraction writes);
        a server ties it to its largest upload (``LODSERVER_ZIP_UNPACKED_RATIO``).
    max_ratio : float
        Largest uncompressed / compressed size of one entry above
        :data:`RATIO_FREE_BYTES`, and of the whole archive.
    max_depth : int
        Folders in an entry's path (``a/b/c.png`` is 2).
    max_name_bytes : int
        UTF-8 bytes of a file name (one path component).
    """

    max_files: int = 64
    max_entries: int = 1024
    max_unpacked_bytes: int = 1 << 30
    max_ratio: float = 100.0
    max_depth: int = 8
    max_name_bytes: int = 200


# The limits of a server that sets none (frozen: safe to share as a default).
DEFAULT_SET_LIMITS = FileSetLimits()


def check_name(name: str, *, what: str = "name", max_bytes: int = MAX_NAME_BYTES) -> str:
    """``name`` if it may be kept as a client gave it: the one rule for every name
    stored, so that SQLite and PostgreSQL catalogues accept exactly the same names.

    Parameters
    ----------
    name : str
        A file's name or the ``name`` form field, as received.
    what : str
        What the name is, for the message ("the file name", "the form field 'name'").
    max_bytes : int
        Most UTF-8 bytes accepted.

    Returns
    -------
    str
        ``name``, unchanged.

    Raises
    ------
    MeshError
        ``name`` holds a control character (C0 including NUL, DEL, C1), is not
        encodable as UTF-8 (a lone surrogate), or is longer than ``max_bytes``.
    """
    found = _CONTROL.search(name)
    if found:
        raise MeshError(f"{what} {name[:60]!r} holds the control character "
                        f"U+{ord(found.group()):04X}; rename it")
    try:
        size = len(name.encode("utf-8"))
    except UnicodeEncodeError:
        raise MeshError(f"{what} {name[:60]!r} is not valid Unicode text") from None
    if size > max_bytes:
        raise MeshError(f"{what} {name[:60]!r}... is {size} bytes long in UTF-8; at most "
                        f"{max_bytes} are accepted")
    return name


def plain_name(name: str, limits: FileSetLimits = DEFAULT_SET_LIMITS) -> str:
    """The base name of a client's file name, if it is safe to create as it is.

    Parameters
    ----------
    name : str
        The name as the client sent it (a browser sends the base name; some
        clients send a path, with ``/`` or ``\\``).

    Returns
    -------
    str
        The last component, unchanged (references in the other files name it so).

    Raises
    ------
    MeshError
        Empty, ``.``/``..``, starting with a dot, with control characters, or
        longer than ``limits.max_name_bytes``.
    """
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    _check_component(base, name, limits)
    return base


def _check_component(part: str, written: str, limits: FileSetLimits) -> None:
    if part in ("", ".", ".."):
        raise MeshError(f"the file name {written!r} names no file")
    if part.startswith("."):
        raise MeshError(f"the file name {written!r} starts with a dot; rename it")
    if ":" in part:
        raise MeshError(f"the file name {written!r} has a colon; rename it")
    check_name(part, what="the file name", max_bytes=limits.max_name_bytes)


def is_mesh_name(name: str) -> bool:
    """Whether ``name`` ends in an extension :func:`~lodserver.io.load_mesh` reads."""
    return PurePosixPath(name).suffix.lower().lstrip(".") in SUPPORTED_INPUT


def pick_main(names, main: str | None = None) -> str:
    """The mesh file of a set: ``main`` if given, else its only mesh file.

    Parameters
    ----------
    names : iterable of str
        The set's files, relative POSIX paths (``textures/a.png``).
    main : str, optional
        The client's choice (the form field ``main``): a path of the set, or a
        base name that only one of its files has.

    Returns
    -------
    str
        One of ``names``.

    Raises
    ------
    NoMeshFile
        No file of the set is a mesh file (and no ``main`` was given).
    MeshError
        ``main`` is not in the set or not a mesh file, or the set holds
        several mesh files and no ``main``.
    """
    names = list(names)
    meshes = [name for name in names if is_mesh_name(name)]
    if main is not None:
        wanted = main.replace("\\", "/").strip("/")
        found = [name for name in names if name == wanted]
        found = found or [name for name in names if PurePosixPath(name).name == wanted]
        if len(found) != 1:
            raise MeshError(f"the form field 'main' names {main!r}, which is "
                            f"{'not one of' if not found else 'more than one of'} the "
                            "uploaded files")
        if not is_mesh_name(found[0]):
            raise MeshError(f"the form field 'main' names {main!r}, which is not a mesh file "
                            f"(one of {_extensions()})")
        return found[0]
    if not meshes:
        shown = ", ".join(repr(name) for name in names[:4]) + (", ..." if len(names) > 4 else "")
        raise NoMeshFile(f"the upload ({shown}) holds no mesh file: include one ending in "
                         f"one of {_extensions()}")
    if len(meshes) > 1:
        shown = ", ".join(repr(name) for name in meshes[:4]) + (", ..." if len(meshes) > 4
                                                               else "")
        raise MeshError(f"the upload holds {len(meshes)} mesh files ({shown}); name the one "
                        "to build in the form field 'main'")
    return meshes[0]


def _extensions() -> str:
    return ", ".join("." + kind for kind in SUPPORTED_INPUT)


# ---- zip archives -------------------------------------------------------------
def _declared_entries(path: Path) -> tuple[int, int]:
    """(entries, central directory bytes) as the archive's end record declares them,
    read from its last 64 KiB before zipfile builds an object per entry (a 256 MB
    archive of empty entries would be millions of them)."""
    with open(path, "rb") as file:
        size = file.seek(0, os.SEEK_END)
        tail_start = max(0, size - (22 + 0xFFFF))
        file.seek(tail_start)
        tail = file.read()
        at = tail.rfind(b"PK\x05\x06")
        if at < 0 or len(tail) - at < 22:
            raise MeshError("the archive is not a zip file (it has no end of central "
                            "directory record)")
        _, _, _, _, entries, cd_bytes, _, _ = struct.unpack_from("<4sHHHHIIH", tail, at)
        if entries == 0xFFFF or cd_bytes == 0xFFFFFFFF:
            # zip64: the real counts are in the zip64 end record, located by its locator
            locator = tail_start + at - 20
            if locator < 0:
                raise MeshError("the archive's zip64 records are malformed")
            file.seek(locator)
            signature, _, offset, _ = struct.unpack("<4sIQI", file.read(20))
            if signature != b"PK\x06\x07" or offset > size - 56:
                raise MeshError("the archive's zip64 records are malformed")
            file.seek(offset)
            record = file.read(56)
            if record[:4] != b"PK\x06\x06":
                raise MeshError("the archive's zip64 records are malformed")
            entries, cd_bytes = struct.unpack_from("<QQ", record, 32)
    return entries, cd_bytes


def _entry_parts(info: zipfile.ZipInfo, limits: FileSetLimits) -> list[str] | None:
    """The path components of an entry, checked; None for junk to skip."""
    written = info.filename
    name = written.replace("\\", "/")
    if "\0" in name:
        raise MeshError(f"the archive entry {written!r} contains a NUL character")
    if name.startswith("/") or re.match(r"^[A-Za-z]:", name):
        raise MeshError(f"the archive entry {written!r} is an absolute path; only relative "
                        "names are extracted")
    parts = [part for part in name.split("/") if part not in ("", ".")]
    if ".." in parts:
        raise MeshError(f"the archive entry {written!r} leads out of the archive's folder "
                        "('..')")
    if not parts:
        return None
    if parts[0] in _JUNK_FOLDERS or any(part.startswith(".") for part in parts):
        return None         # __MACOSX/, .DS_Store, ._file: archivers' junk, never a mesh's
    if len(parts) - 1 > limits.max_depth:
        raise MeshError(f"the archive entry {written!r} is more than {limits.max_depth} "
                        "folders deep")
    for part in parts:
        _check_component(part, written, limits)
    return parts


def _entry_kind(info: zipfile.ZipInfo) -> str:
    """'dir' or 'file'; anything else (a symlink, a device) is refused."""
    mode = info.external_attr >> 16
    kind = stat.S_IFMT(mode)
    if info.flag_bits & 0x1:
        raise MeshError(f"the archive entry {info.filename!r} is encrypted; send it "
                        "unencrypted")
    if kind == stat.S_IFLNK:
        raise MeshError(f"the archive entry {info.filename!r} is a symbolic link, which is "
                        "not extracted from an upload")
    if info.is_dir() and kind in (0, stat.S_IFDIR):
        return "dir"
    if kind not in (0, stat.S_IFREG):
        raise MeshError(f"the archive entry {info.filename!r} is not a regular file")
    return "file"


def _checked_entries(archive: zipfile.ZipFile, limits: FileSetLimits
                     ) -> list[tuple[zipfile.ZipInfo, list[str], str]]:
    """Every entry to extract with its parts and kind, after every check of the module
    docstring; raises before anything is written."""
    entries, seen, total, packed = [], {}, 0, 0
    infos = archive.infolist()
    if len(infos) > limits.max_entries:
        raise LimitError(f"the archive has {len(infos)} entries; an upload may have at most "
                         f"{limits.max_entries}")
    for info in infos:
        parts = _entry_parts(info, limits)
        if parts is None:
            continue
        kind = _entry_kind(info)
        key = "/".join(parts)
        if key in seen and not (kind == "dir" and seen[key] == "dir"):
            raise MeshError(f"the archive holds {key!r} more than once")
        for depth in range(1, len(parts)):
            if seen.get("/".join(parts[:depth])) == "file":
                raise MeshError(f"the archive entry {info.filename!r} is inside "
                                f"{'/'.join(parts[:depth])!r}, which is a file")
        if kind == "file" and any(other.startswith(key + "/") for other in seen):
            raise MeshError(f"the archive holds {key!r} both as a file and as a folder")
        seen[key] = kind
        if kind == "dir":
            continue
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED,
                                      zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA):
            raise MeshError(f"the archive entry {info.filename!r} uses a compression method "
                            f"({info.compress_type}) that is not supported; use deflate")
        total += info.file_size
        packed += info.compress_size
        if total > limits.max_unpacked_bytes:
            raise LimitError(f"the archive's files add up to more than "
                             f"{limits.max_unpacked_bytes} bytes uncompressed; an upload may "
                             "unpack to at most that")
        if (info.file_size > RATIO_FREE_BYTES
                and info.file_size > limits.max_ratio * max(info.compress_size, 1)):
            raise LimitError(f"the archive entry {info.filename!r} expands "
                             f"{info.file_size / max(info.compress_size, 1):.0f} times; an "
                             f"upload's entries may expand at most {limits.max_ratio:g} times")
        entries.append((info, parts, kind))
    if total > RATIO_FREE_BYTES and total > limits.max_ratio * max(packed, 1):
        raise LimitError(f"the archive expands {total / max(packed, 1):.0f} times; an upload "
                         f"may expand at most {limits.max_ratio:g} times")
    return entries


def _check_declared(path: Path, limits: FileSetLimits) -> None:
    """Refuse an archive whose end record declares too many entries, before zipfile
    reads its central directory."""
    entries, cd_bytes = _declared_entries(path)
    # each central-directory entry is 46 bytes plus its name, extra field and comment
    if entries > limits.max_entries or cd_bytes > limits.max_entries * 1024 + 65536:
        raise LimitError(f"the archive declares {entries} entries in {cd_bytes} bytes; an "
                         f"upload may have at most {limits.max_entries} entries")


def _unreadable(exc: BaseException) -> MeshError:
    # BadZipFile also says "Bad CRC-32 for file ..." naming only the entry
    return MeshError(f"the archive is not a readable zip file ({exc})")


# zipfile's own failures on a malformed archive (a ValueError among them)
_ZIP_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, NotImplementedError,
               UnicodeDecodeError, ValueError)


def list_zip(path, limits: FileSetLimits = DEFAULT_SET_LIMITS) -> list[str]:
    """The files a client's zip would unpack to, after every check of :func:`unpack_zip`
    that needs no decompression: nothing is extracted.

    Parameters
    ----------
    path : path of the archive.
    limits : FileSetLimits

    Returns
    -------
    list of str
        The files, as relative POSIX paths, in archive order (junk skipped).

    Raises
    ------
    MeshError, LimitError
        As :func:`unpack_zip`, but a corrupt entry (its CRC) is found only
        when it is unpacked.

    Reads only the end record and the central directory (bounded by
    ``limits.max_entries``): safe to run in the server process.
    """
    path = Path(path)
    _check_declared(path, limits)
    try:
        with zipfile.ZipFile(path) as archive:
            return ["/".join(parts) for _, parts, kind in _checked_entries(archive, limits)
                    if kind == "file"]
    except MeshError:
        raise
    except _ZIP_ERRORS as exc:
        raise _unreadable(exc) from None


def name_main(archive, main: str) -> None:
    """Write ``main`` into the comment of ``archive``, a zip :func:`list_zip` accepted,
    so :func:`open_set` finds the main file: only its central directory is rewritten
    in place, its compressed entries stay as they are."""
    try:
        with zipfile.ZipFile(archive, "a") as opened:
            opened.comment = _MAIN_TAG + main.encode("utf-8")
    except _ZIP_ERRORS as exc:
        raise _unreadable(exc) from None


def unpack_zip(path, folder, limits: FileSetLimits = DEFAULT_SET_LIMITS) -> list[str]:
    """Extract a client's zip into ``folder``, after checking all of it.

    Parameters
    ----------
    path : path of the archive.
    folder : path of an empty folder (it must exist) to extract into.
    limits : FileSetLimits

    Returns
    -------
    list of str
        The files written, as relative POSIX paths, in archive order (junk
        such as ``__MACOSX/`` and dot files is skipped).

    Raises
    ------
    MeshError, LimitError
        The archive is not a zip, is malformed or corrupt (a CRC mismatch), or
        breaks a rule of the module docstring; nothing is left in ``folder``
        but what was extracted before a corrupt entry was found (the caller
        removes ``folder``).
    """
    path, folder = Path(path), Path(folder)
    _check_declared(path, limits)
    try:
        with zipfile.ZipFile(path) as archive:
            written = []
            for info, parts, kind in _checked_entries(archive, limits):
                if kind == "dir":
                    _make_folders(folder, parts)
                    continue
                _extract_file(archive, info, parts, folder)
                written.append("/".join(parts))
            return written
    except MeshError:       # a ValueError too: not to be taken for zipfile's own
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, NotImplementedError,
            UnicodeDecodeError, ValueError) as exc:
        raise _unreadable(exc) from None


def _extract_file(archive: zipfile.ZipFile, info: zipfile.ZipInfo, parts: list[str],
                  folder: Path) -> None:
    """Write one checked entry to ``folder/parts...``, a new file in folders made here;
    zipfile stops it at its declared size and checks its CRC."""
    _make_folders(folder, parts[:-1])
    flags = (os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
             | getattr(os, "O_CLOEXEC", 0))
    with archive.open(info) as source, \
            open(os.open(folder.joinpath(*parts), flags, 0o600), "wb") as out:
        shutil.copyfileobj(source, out, 1 << 20)


def _make_folders(folder: Path, parts: list[str]) -> None:
    """Create ``folder/parts...`` one level at a time, refusing anything but a folder
    we made (extraction only ever creates folders and regular files)."""
    here = folder
    for part in parts:
        here = here / part
        try:
            here.mkdir()
        except FileExistsError:
            if not stat.S_ISDIR(os.lstat(here).st_mode):
                raise MeshError(f"the archive holds {part!r} both as a file and as a "
                                "folder") from None


def pack_set(folder, names, archive, *, main: str) -> None:
    """Write the files ``names`` of ``folder`` into one zip, uncompressed, naming ``main``.

    Parameters
    ----------
    folder : path holding the set's files.
    names : relative POSIX paths of the files (from :func:`plain_name` or
        :func:`unpack_zip`).
    archive : path of the zip to write (outside the names).
    main : the main file's name, one of ``names`` (kept in the zip comment).

    Stored, not deflated: textures and GLB buffers are compressed already, and the
    archive only lives until the mesh is built.
    """
    folder = Path(folder)
    with zipfile.ZipFile(archive, "x", compression=zipfile.ZIP_STORED,
                         allowZip64=True) as out:
        for name in names:
            out.write(folder / name, name)
        out.comment = _MAIN_TAG + main.encode("utf-8")


@contextmanager
def open_set(archive, folder, limits: FileSetLimits = DEFAULT_SET_LIMITS):
    """Open a set's archive for one load: yields the path of its main file in ``folder``.

    Parameters
    ----------
    archive : path of the set's zip (an uploaded zip, or :func:`pack_set`'s).
    folder : path of an empty folder (it must exist), the load's ``root``.
    limits : FileSetLimits

    Every entry is checked first, as by :func:`unpack_zip`. The main file is the
    one the archive's comment names (:func:`name_main`, :func:`pack_set`), else
    its only mesh file (:func:`pick_main`); only it is extracted at once, and
    any other file only when a reference of the mesh names it, while the block
    runs (``io.references.extract_on_demand``): files of the set the mesh never
    names are never written. The archive stays open until the block ends.

    Raises
    ------
    MeshError, LimitError
        As :func:`unpack_zip` (a corrupt entry when it is extracted), or as
        :func:`pick_main`.
    """
    path, folder = Path(archive), Path(folder)
    _check_declared(path, limits)
    try:
        opened = zipfile.ZipFile(path)
    except _ZIP_ERRORS as exc:
        raise _unreadable(exc) from None
    with opened:
        try:
            files = {"/".join(parts): (info, parts)
                     for info, parts, kind in _checked_entries(opened, limits) if kind == "file"}
        except MeshError:
            raise
        except _ZIP_ERRORS as exc:
            raise _unreadable(exc) from None
        comment = opened.comment
        main = comment[len(_MAIN_TAG):].decode("utf-8", "replace") \
            if comment.startswith(_MAIN_TAG) else None
        chosen = pick_main(list(files), main)
        extracted = set()

        def extract(parts: list[str]) -> None:
            key = "/".join(parts)
            if key in files and key not in extracted:
                extracted.add(key)
                try:
                    _extract_file(opened, *files[key], folder)
                except MeshError:
                    raise
                except _ZIP_ERRORS as exc:
                    raise _unreadable(exc) from None

        extract(files[chosen][1])
        with extract_on_demand(folder, extract):
            yield folder / chosen


def load_warnings(report: dict | None) -> list[str]:
    """Sentences for what a load left out (a ``LoadReport.as_dict()``), for the client.

    Parameters
    ----------
    report : dict or None
        ``missing_files`` (companion files named but absent) and
        ``dropped_attributes`` (per-vertex data not kept) are reported.
    """
    if not report:
        return []
    warnings = [f"{name!r} is named by the mesh but was not uploaded, so its materials are "
                "plain; upload it together with the mesh" for name in report.get(
                    "missing_files") or []]
    dropped = report.get("dropped_attributes") or []
    if dropped:
        warnings.append(f"not kept: {', '.join(dropped)} (lodserver keeps positions, normals, "
                        "UVs and colours)")
    return warnings
