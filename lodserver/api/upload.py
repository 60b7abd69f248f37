"""Receiving ``POST /meshes``: a multipart body streamed into the data directory.

The body is parsed as it arrives (python-multipart's streaming parser) and
each file part is written, a batch of chunks at a time in a worker thread, to
a folder of its own under ``<data_dir>/tmp/``: never through the system temp
directory, never copied again, and never a disk write on the event loop. The
folder holds only the uploaded files, which is the ``root`` their references
must resolve in. The body is counted while it streams in, so an oversized
upload is refused (413) as soon as it passes the limit, before it is all read;
a ``Content-Length`` already over the limit is refused before reading anything.
On any failure the folder and what was written into it are removed; whatever
a killed process leaves there, the store removes when it next opens.

A body that arrives too slowly holds a socket, an open file and a folder for
nothing, so it is cut (408, the connection closed) when it sends nothing for
``UploadPace.idle_seconds``, or less than ``UploadPace.min_rate`` on average
over a period of waiting for it; only the time spent waiting for the client
counts, so a server slow to write never blames its client. And only so many
bodies are received at once (:class:`UploadSlots`); past that, 503 before a
byte of the body is read.

An upload is one mesh file, or a set (:mod:`lodserver.io.fileset`): several
``file`` parts (an OBJ with its MTL and textures, a ``.gltf`` with its
``.bin`` and images) or one ``.zip`` of them. :func:`prepare_source` turns a
set into the one archive the store keeps, after picking its main file: a zip
is checked and kept as it came, compressed, and is unpacked only by its parse.
"""

from __future__ import annotations

import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path, PurePath

import anyio
from fastapi import HTTPException, Request
from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect

from ..io import SUPPORTED_INPUT
from ..io.fileset import (DEFAULT_SET_LIMITS, FileSetLimits, NoMeshFile, check_name, list_zip,
                          name_main, pack_set, pick_main, plain_name)
from ..io.limits import LimitError
from ..mesh import MeshError
from ..service.parsing import RETRY_AFTER, SET_TYPE, ParserBusy
from ..service.store import StorageFullError, Store, is_disk_full

# Form fields beside the files: a handful of build options, each short.
MAX_FIELDS = 16
MAX_FIELD_BYTES = 64 * 2**10
# Body bytes handed to the writer thread at once: few thread hops, little memory.
BATCH_BYTES = 1 * 2**20
# A lone mesh file's name is kept on disk (the loader's messages name the file
# by it) if it is this plain: letters, digits and a little punctuation, not
# starting with a dot; else it is saved under a fixed name. The files of a set
# must keep their names (they name each other), so they follow io.fileset.plain_name.
_PLAIN_NAME = re.compile(r"[^\W][\w .+,()\-]*")
# Where a set's archive goes inside the upload's folder: a name starting with a
# dot, which no uploaded file may have (plain_name), so it never clashes.
_ARCHIVE = ".set.zip"


class UnsupportedUpload(MeshError):
    """The body is not multipart, or the file's type is not one lodserver reads."""


class UploadsBusy(ParserBusy):
    """As many upload bodies as the server receives at once are arriving (503, Retry-After)."""


@dataclass(frozen=True)
class UploadPace:
    """How slowly an upload's body may arrive before it is cut.

    idle_seconds : float
        Longest wait for the next bytes of the body (the first ones included).
    min_rate : float
        Bytes per second the body must average over each ``rate_seconds`` of
        waiting for it; 0: no minimum.
    rate_seconds : float
        The period ``min_rate`` is measured over; the first is a new upload's grace.
    """

    idle_seconds: float = 30.0
    min_rate: float = 1024.0
    rate_seconds: float = 30.0


DEFAULT_PACE = UploadPace()


class UploadSlots:
    """At most ``size`` bodies received at once, counted on the event loop (one thread)."""

    def __init__(self, size: int):
        self.size, self.taken = size, 0

    def take(self) -> None:
        """Count one more body; :class:`UploadsBusy` if all slots are taken."""
        if self.taken >= self.size:
            raise UploadsBusy(f"the server is already receiving {self.taken} uploads; try "
                              f"again in {RETRY_AFTER} seconds")
        self.taken += 1

    def give_back(self) -> None:
        self.taken -= 1


def _too_slow(message: str) -> HTTPException:
    # the client may still be sending: the connection is closed after the answer
    return HTTPException(408, message, headers={"Connection": "close"})


class _Clock:
    """The time spent waiting for a body and the bytes it brought, checked
    against an :class:`UploadPace` one period at a time."""

    def __init__(self, pace: UploadPace):
        self.pace, self.waited, self.received = pace, 0.0, 0

    def count(self, received: int, waited: float) -> None:
        pace = self.pace
        self.waited += waited
        self.received += received
        if self.waited < pace.rate_seconds:
            return
        if pace.min_rate and self.received < pace.min_rate * self.waited:
            raise _too_slow(f"the upload arrived at {self.received / self.waited:.0f} bytes "
                            f"per second; this server needs at least {pace.min_rate:g}")
        self.waited, self.received = 0.0, 0


@dataclass
class Upload:
    """A received upload: its files on local disk (alone in ``folder``), as
    ``(name as the client gave it, path)`` pairs in form order, and the other
    form fields. ``path``, ``filename`` and ``file_type`` are the first file's."""

    folder: Path
    files: list[tuple[str, Path]] = field(default_factory=list)
    fields: dict[str, str] = field(default_factory=dict)

    @property
    def path(self) -> Path:
        return self.files[0][1]

    @property
    def filename(self) -> str:
        return self.files[0][0]

    @property
    def file_type(self) -> str:
        return PurePath(self.filename).suffix.lower().lstrip(".")

    def discard(self) -> None:
        """Remove the folder and whatever is still in it."""
        shutil.rmtree(self.folder, ignore_errors=True)


@dataclass(frozen=True)
class Source:
    """What the store keeps for an upload and how to parse it: ``path`` (a mesh
    file, or a set's archive of :data:`SET_TYPE`) inside ``root``; ``name`` the
    main file's name as uploaded; ``files`` every file of the set (one for a lone file)."""

    path: Path
    root: Path
    name: str
    file_type: str
    files: tuple[str, ...]


class _FormWriter:
    """The multipart parser's callbacks: fields kept in memory (bounded), the file
    parts written to ``folder``. Fed from a worker thread, one call at a time."""

    def __init__(self, boundary: bytes, folder: Path, limits: FileSetLimits = DEFAULT_SET_LIMITS):
        self.folder = folder
        self.limits = limits
        self.fields: dict[str, str] = {}
        self.upload = Upload(folder)
        self.ended = False
        self._headers: dict[bytes, bytes] = {}
        self._header_field = b""
        self._header_value = b""
        self._name: str | None = None
        self._value = bytearray()
        self._file = None
        self._parts = 0
        self._parser = MultipartParser(boundary, {
            "on_part_begin": self._part_begin, "on_header_field": self._header_field_data,
            "on_header_value": self._header_value_data, "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished, "on_part_data": self._part_data,
            "on_part_end": self._part_end, "on_end": self._end})

    def feed(self, chunks: list[bytes]) -> None:
        try:
            for chunk in chunks:
                self._parser.write(chunk)
        except MultipartParseError as exc:
            raise MeshError(f"the multipart body is malformed: {exc}") from None

    def finish(self) -> Upload:
        self.close()
        if not self.ended:
            raise MeshError("the multipart body ends before its closing boundary")
        if not self.upload.files:
            raise MeshError("the form has no file in the field 'file'")
        self.upload.fields = self.fields
        return self.upload

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    # ---- callbacks ----------------------------------------------------------
    def _part_begin(self):
        self._parts += 1
        if self._parts > MAX_FIELDS + self.limits.max_files:
            raise MeshError(f"the form has more than {MAX_FIELDS} fields and "
                            f"{self.limits.max_files} files")
        self._headers, self._name = {}, None
        self._value.clear()

    def _header_field_data(self, data, start, end):
        self._header_field += data[start:end]

    def _header_value_data(self, data, start, end):
        self._header_value += data[start:end]

    def _header_end(self):
        self._headers[self._header_field.strip().lower()] = self._header_value.strip()
        self._header_field, self._header_value = b"", b""

    def _headers_finished(self):
        kind, options = parse_options_header(self._headers.get(b"content-disposition", b""))
        if kind != b"form-data" or b"name" not in options:
            raise MeshError("a part of the form has no Content-Disposition name")
        self._name = options[b"name"].decode("utf-8", "replace")
        if b"filename" not in options:
            return
        if self._name != "file":
            raise MeshError(f"the form's files must be in the field 'file', not {self._name!r}")
        files = self.upload.files
        if len(files) >= self.limits.max_files:
            raise MeshError(f"the form holds more than {self.limits.max_files} files")
        written = options[b"filename"].decode("utf-8", "replace")
        # the base name is what is kept (catalogue, messages); refused before its bytes are read
        filename = check_name(PurePath(written.replace("\\", "/")).name or "upload",
                              what="the file name")
        file_type = PurePath(filename).suffix.lower().lstrip(".")
        if file_type in SUPPORTED_INPUT:
            # nothing names a mesh file, so an unusual name is replaced (the
            # client's is kept for messages and the catalogue)
            plain = _PLAIN_NAME.fullmatch(filename) and len(filename.encode()) <= 200
            disk_name = filename if plain else f"upload-{len(files)}.{file_type}"
        else:
            disk_name = plain_name(filename, self.limits)   # other files name it as it is
        if any(path.name == disk_name for _, path in files):
            raise MeshError(f"the form holds two files named {disk_name!r}; file names must "
                            "differ")
        path = self.folder / disk_name
        files.append((filename, path))
        self._file = open(path, "xb")

    def _part_data(self, data, start, end):
        if self._file is not None:
            self._file.write(data[start:end])
            return
        self._value += data[start:end]
        if len(self._value) > MAX_FIELD_BYTES:
            raise MeshError(f"form field {self._name!r} is longer than {MAX_FIELD_BYTES} bytes")

    def _part_end(self):
        if self._file is not None:
            self.close()
        elif self._name is not None:
            if self._name in self.fields or len(self.fields) >= MAX_FIELDS:
                raise MeshError(f"form field {self._name!r} is repeated" if self._name in
                                self.fields else f"the form has more than {MAX_FIELDS} fields "
                                "beside the file")
            self.fields[self._name] = self._value.decode("utf-8", "replace")

    def _end(self):
        self.ended = True


def prepare_source(upload: Upload, *, main: str | None,
                   limits: FileSetLimits = DEFAULT_SET_LIMITS) -> Source:
    """What to parse and store for ``upload``: a lone mesh file as it is, a set as one archive.

    Parameters
    ----------
    upload : Upload
    main : str, optional
        The form field ``main``: which file of a set is the mesh.
    limits : FileSetLimits

    Raises
    ------
    UnsupportedUpload
        No file of the upload is a mesh file (415).
    MeshError
        A zip sent with other files, a ``main`` that names no mesh file of the
        set, several mesh files and no ``main``, or a zip breaking the rules
        of :mod:`lodserver.io.fileset`.

    A zip is listed, not unpacked (``io.fileset.list_zip``: its central
    directory only), and kept compressed with the main file named in its
    comment; its parse unpacks it once. Blocking (it may copy a set of form
    parts into one archive): call it from a thread.
    """
    files = upload.files
    kinds = [PurePath(name).suffix.lower() for name, _ in files]
    names = [path.name for _, path in files]
    if ".zip" in kinds:
        if len(files) > 1:
            raise MeshError("send either one .zip or the files themselves, not both")
        names = list_zip(upload.path, limits)
    elif len(files) == 1 and main is None:
        name, path = files[0]
        if upload.file_type not in SUPPORTED_INPUT:
            raise UnsupportedUpload(f"cannot read {name!r}: the file name must end in one of "
                                    f"{', '.join('.' + kind for kind in SUPPORTED_INPUT)}, "
                                    "or be a .zip of a mesh and its files")
        return Source(path, upload.folder, name, upload.file_type, (name,))
    try:
        chosen = pick_main(names, main)
    except NoMeshFile as exc:
        raise UnsupportedUpload(str(exc)) from None
    # the name the client gave the main file (a lone file may have been renamed on disk)
    name = next((client for client, path in files if path.name == chosen),
                PurePath(chosen).name)
    if ".zip" in kinds:
        name_main(upload.path, chosen)
        return Source(upload.path, upload.folder, name, SET_TYPE, tuple(names))
    if len(files) == 1:
        return Source(upload.path, upload.folder, name, upload.file_type, (name,))
    archive = upload.folder / _ARCHIVE
    pack_set(upload.folder, names, archive, main=chosen)
    return Source(archive, upload.folder, name, SET_TYPE, tuple(names))


def _boundary(content_type: str) -> bytes:
    kind, options = parse_options_header(content_type)
    if kind != b"multipart/form-data":
        raise UnsupportedUpload("send the mesh as multipart/form-data with the file in the field "
                                "'file'")
    boundary = options.get(b"boundary")
    if not boundary or len(boundary) > 200:
        raise MeshError("the multipart/form-data content type has no usable boundary")
    return boundary


async def _next_chunk(stream, pace: UploadPace, clock: _Clock) -> bytes | None:
    """The next chunk of the body (None at its end), within the pace's limits."""
    started = time.monotonic()
    try:
        with anyio.fail_after(pace.idle_seconds):
            chunk = await stream.__anext__()
    except StopAsyncIteration:
        return None
    except TimeoutError:
        raise _too_slow(f"the upload sent nothing for {pace.idle_seconds:g} seconds") from None
    clock.count(len(chunk), time.monotonic() - started)
    return chunk


async def receive_upload(request: Request, *, limit: int, store: Store,
                         limits: FileSetLimits = DEFAULT_SET_LIMITS,
                         pace: UploadPace = DEFAULT_PACE) -> Upload:
    """Stream the multipart body of ``request`` into a new folder of ``store.scratch``.

    Parameters
    ----------
    request : the incoming request
    limit : int
        Largest body accepted, in bytes.
    store : Store
        Where the folder is made (``<data_dir>/tmp/``).
    limits : FileSetLimits
        How many files the form may hold, and their names.
    pace : UploadPace
        How slowly the body may arrive.

    Returns
    -------
    Upload
        Its ``discard()`` must be called once the file has been used.

    Raises
    ------
    LimitError
        The body is larger than ``limit``.
    HTTPException
        408: the body sent nothing for ``pace.idle_seconds``, or arrived slower
        than ``pace.min_rate``.
    UnsupportedUpload
        Not multipart/form-data.
    MeshError
        The form is malformed, has too many or too long fields or too many
        files, two files of one name, a file name that is not plain (see
        ``io.fileset.plain_name``), or no ``file`` field.
    StorageFullError
        The disk ran out of space while writing the file.
    """
    boundary = _boundary(request.headers.get("content-type", ""))
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise LimitError(f"the upload is {int(declared)} bytes; this server accepts at most "
                         f"{limit}")
    folder = await anyio.to_thread.run_sync(lambda: store.scratch(prefix="upload-"))
    writer = _FormWriter(boundary, folder, limits)
    try:
        total, batch, batched = 0, [], 0
        stream, clock = request.stream().__aiter__(), _Clock(pace)
        while (chunk := await _next_chunk(stream, pace, clock)) is not None:
            total += len(chunk)
            if total > limit:
                raise LimitError(f"the upload is larger than this server's limit of {limit} bytes")
            batch.append(chunk)
            batched += len(chunk)
            if batched >= BATCH_BYTES:
                await anyio.to_thread.run_sync(writer.feed, batch)
                batch, batched = [], 0
        if batch:
            await anyio.to_thread.run_sync(writer.feed, batch)
        return await anyio.to_thread.run_sync(writer.finish)
    except BaseException as exc:
        # also on cancellation (the client went away): synchronous, so it runs
        writer.close()
        shutil.rmtree(folder, ignore_errors=True)
        if is_disk_full(exc):
            raise StorageFullError("the server ran out of disk space while receiving the "
                                   "upload; try again later") from None
        if isinstance(exc, ClientDisconnect):
            # nobody reads the answer; a 4xx keeps it out of the error log
            raise MeshError("the client closed the connection before the upload was "
                            "complete") from None
        raise
