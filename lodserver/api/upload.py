"""Receiving ``POST /meshes``: a multipart body streamed to a temporary file.

The request body is counted while it streams in, so an oversized upload is
refused (413) as soon as it passes the limit, before it is all read; a
``Content-Length`` already over the limit is refused before reading anything.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path, PurePath

from fastapi import Request
from starlette.datastructures import UploadFile
from starlette.formparsers import MultiPartException, MultiPartParser

from ..io import SUPPORTED_INPUT
from ..jobs import LimitError
from ..mesh import MeshError

# Form fields beside the file: a handful of build options.
MAX_FIELDS = 16


class UnsupportedUpload(MeshError):
    """The body is not multipart, or the file's type is not one lodserver reads."""


@dataclass
class Upload:
    """A received upload: the file on local disk, its name and type, the other fields."""

    path: Path
    filename: str
    file_type: str
    fields: dict[str, str]


async def receive_upload(request: Request, *, limit: int) -> Upload:
    """Stream the multipart body of ``request`` into a temporary file.

    Parameters
    ----------
    request : the incoming request
    limit : int
        Largest body accepted, in bytes.

    Raises
    ------
    LimitError
        The body is larger than ``limit``.
    UnsupportedUpload
        Not multipart/form-data, or the file's extension is not supported.
    MeshError
        The form is malformed or has no ``file`` field.
    """
    if not request.headers.get("content-type", "").startswith("multipart/form-data"):
        raise UnsupportedUpload("send the mesh as multipart/form-data with the file in the field "
                                "'file'")
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise LimitError(f"the upload is {int(declared)} bytes; this server accepts at most {limit}")

    async def counted():
        total = 0
        async for chunk in request.stream():
            total += len(chunk)
            if total > limit:
                raise LimitError(f"the upload is larger than this server's limit of {limit} bytes")
            yield chunk

    parser = MultiPartParser(request.headers, counted(), max_files=1, max_fields=MAX_FIELDS)
    try:
        form = await parser.parse()
    except MultiPartException as exc:
        raise MeshError(f"the multipart body is malformed: {exc.message}") from exc
    try:
        file = form.get("file")
        if not isinstance(file, UploadFile):
            raise MeshError("the form has no file in the field 'file'")
        filename = PurePath(file.filename or "").name or "upload"
        file_type = PurePath(filename).suffix.lower().lstrip(".")
        if file_type not in SUPPORTED_INPUT:
            raise UnsupportedUpload(f"cannot read {filename!r}: the file name must end in one of "
                                    f"{', '.join('.' + kind for kind in SUPPORTED_INPUT)}")
        fields = {key: value for key, value in form.multi_items()
                  if key != "file" and isinstance(value, str)}
        with tempfile.NamedTemporaryFile(prefix="lodserver-upload-", suffix=f".{file_type}",
                                         delete=False) as out:
            file.file.seek(0)
            shutil.copyfileobj(file.file, out)
        return Upload(Path(out.name), filename, file_type, fields)
    finally:
        await form.close()
