"""Receiving ``POST /meshes``: a multipart body streamed into the data directory.

The body is parsed as it arrives (python-multipart's streaming parser) and the
file part is written, a batch of chunks at a time in a worker thread, to a
folder of its own under ``<data_dir>/tmp/``: never through the system temp
directory, never copied again, and never a disk write on the event loop. The
folder holds only the uploaded file, which is the ``root`` its references must
resolve in. The body is counted while it streams in, so an oversized upload is
refused (413) as soon as it passes the limit, before it is all read; a
``Content-Length`` already over the limit is refused before reading anything.
On any failure the folder and what was written into it are removed; whatever
a killed process leaves there, the store removes when it next opens.
"""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path, PurePath

import anyio
from fastapi import Request
from starlette.requests import ClientDisconnect
from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

from ..io import SUPPORTED_INPUT
from ..io.limits import LimitError
from ..mesh import MeshError
from ..service.store import Store, StorageFullError, is_disk_full

# Form fields beside the file: a handful of build options, each short.
MAX_FIELDS = 16
MAX_FIELD_BYTES = 64 * 2**10
# Body bytes handed to the writer thread at once: few thread hops, little memory.
BATCH_BYTES = 1 * 2**20
# File names used as they are on disk: letters, digits and a little punctuation,
# not starting with a dot (the extension check already refuses "." and "..").
_PLAIN_NAME = re.compile(r"[^\W][\w .+,()\-]*")


class UnsupportedUpload(MeshError):
    """The body is not multipart, or the file's type is not one lodserver reads."""


@dataclass
class Upload:
    """A received upload: the file on local disk (alone in ``folder``), its name
    and type as the client gave them, and the other form fields."""

    path: Path
    folder: Path
    filename: str
    file_type: str
    fields: dict[str, str] = field(default_factory=dict)

    def discard(self) -> None:
        """Remove the folder and whatever is still in it."""
        shutil.rmtree(self.folder, ignore_errors=True)


class _FormWriter:
    """The multipart parser's callbacks: fields kept in memory (bounded), the file
    part written to ``folder``. Fed from a worker thread, one call at a time."""

    def __init__(self, boundary: bytes, folder: Path):
        self.folder = folder
        self.fields: dict[str, str] = {}
        self.upload: Upload | None = None
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
        if self.upload is None:
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
        if self._parts > MAX_FIELDS + 1:
            raise MeshError(f"the form has more than {MAX_FIELDS} fields beside the file")
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
            raise MeshError(f"the form's file must be in the field 'file', not {self._name!r}")
        if self.upload is not None:
            raise MeshError("the form holds more than one file in the field 'file'")
        filename = PurePath(options[b"filename"].decode("utf-8", "replace")
                            .replace("\\", "/")).name or "upload"
        file_type = PurePath(filename).suffix.lower().lstrip(".")
        if file_type not in SUPPORTED_INPUT:
            raise UnsupportedUpload(f"cannot read {filename!r}: the file name must end in one of "
                                    f"{', '.join('.' + kind for kind in SUPPORTED_INPUT)}")
        # the client's name (the loader's messages name the file by it) if it is
        # a plain one, else a fixed one; alone in a folder of its own either way
        plain = _PLAIN_NAME.fullmatch(filename) and len(filename.encode()) <= 200
        path = self.folder / (filename if plain else f"upload.{file_type}")
        self.upload = Upload(path, self.folder, filename, file_type)
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


def _boundary(content_type: str) -> bytes:
    kind, options = parse_options_header(content_type)
    if kind != b"multipart/form-data":
        raise UnsupportedUpload("send the mesh as multipart/form-data with the file in the field "
                                "'file'")
    boundary = options.get(b"boundary")
    if not boundary or len(boundary) > 200:
        raise MeshError("the multipart/form-data content type has no usable boundary")
    return boundary


async def receive_upload(request: Request, *, limit: int, store: Store) -> Upload:
    """Stream the multipart body of ``request`` into a new folder of ``store.scratch``.

    Parameters
    ----------
    request : the incoming request
    limit : int
        Largest body accepted, in bytes.
    store : Store
        Where the folder is made (``<data_dir>/tmp/``).

    Returns
    -------
    Upload
        Its ``discard()`` must be called once the file has been used.

    Raises
    ------
    LimitError
        The body is larger than ``limit``.
    UnsupportedUpload
        Not multipart/form-data, or the file's extension is not supported.
    MeshError
        The form is malformed, has too many or too long fields, or has no
        ``file`` field.
    StorageFullError
        The disk ran out of space while writing the file.
    """
    boundary = _boundary(request.headers.get("content-type", ""))
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise LimitError(f"the upload is {int(declared)} bytes; this server accepts at most "
                         f"{limit}")
    folder = await anyio.to_thread.run_sync(lambda: store.scratch(prefix="upload-"))
    writer = _FormWriter(boundary, folder)
    try:
        total, batch, batched = 0, [], 0
        async for chunk in request.stream():
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
