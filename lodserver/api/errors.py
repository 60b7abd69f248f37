"""Domain errors -> HTTP status codes, in one place.

=========================  ====  ==============================================
error                      code  when
=========================  ====  ==============================================
UnknownMeshError           404   no mesh has the id (or it is malformed)
AbsentError                404   the mesh has no materials, or no such image
NotReadyError              409   the mesh is queued, building, failed, or its
                                 artefact was found corrupt (and quarantined)
LimitError                 413   upload larger than allowed, too many triangles,
                                 or its parse ran out of memory
UnsupportedUpload          415   not multipart, or a file type lodserver cannot read
MeshError, LevelError      422   not a mesh / bad level parameters
RequestValidationError     422   parameters of the wrong type or range
ParserBusy                 503   the parse queue is full (with Retry-After)
StoreUnavailable           503   the object store cannot be reached (Retry-After)
OSError, SQLite errors     503   the server cannot use its storage right now
StorageFullError           507   the disk is full (also ENOSPC, SQLITE_FULL)
ArtefactError, PacketError 500   an encoder is broken (a bug)
anything else              500   a bug: one generic sentence, details in the log
=========================  ====  ==============================================

Bodies are always ``{"message": "..."}``: one sentence, which never names a
server path (the data directory and the temporary directory are scrubbed
from every message as a last guard; the code raising names the upload instead).
"""

from __future__ import annotations

import logging
import re
import sqlite3
import tempfile

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException

from ..service.materials import AbsentError
from ..progressive.artefact import ArtefactError
from ..io.limits import LimitError
from ..service.parsing import ParserBusy
from ..mesh import MeshError
from ..packets import PacketError
from ..service.errors import StoreUnavailable
from ..service.store import NotReadyError, StorageFullError, UnknownMeshError, is_disk_full
from .upload import UnsupportedUpload

log = logging.getLogger(__name__)

_STATUS = {UnknownMeshError: 404, AbsentError: 404, NotReadyError: 409, LimitError: 413,
           UnsupportedUpload: 415, MeshError: 422, StorageFullError: 507}
_DISK_FULL = "the server has run out of disk space; try again later"


def scrub_paths(message: str, roots) -> str:
    """``message`` with every path under one of ``roots`` replaced by "a server file"."""
    for root in sorted({str(root).rstrip("/") for root in roots if root}, key=len,
                       reverse=True):
        if len(root) > 1:
            message = re.sub(re.escape(root) + r"(/[^\s'\":;,()]*)?", "a server file", message)
    return message


def _server_paths(request: Request) -> list[str]:
    roots = [tempfile.gettempdir()]
    store = getattr(request.app.state, "store", None)
    settings = getattr(request.app.state, "settings", None)
    for root in (getattr(store, "root", None), getattr(settings, "data_dir", None)):
        if root is not None:
            roots += [str(root), str(root.absolute()), str(root.resolve())]
    return roots


def _message(status: int, message: str, headers=None, request: Request | None = None
             ) -> JSONResponse:
    if request is not None:
        message = scrub_paths(message, _server_paths(request))
    return JSONResponse({"message": message}, status_code=status, headers=headers)


async def _domain_error(request: Request, exc: Exception) -> JSONResponse:
    status = next(code for kind, code in _STATUS.items() if isinstance(exc, kind))
    return _message(status, str(exc), request=request)


async def _busy(request: Request, exc: ParserBusy) -> JSONResponse:
    return _message(503, str(exc), {"Retry-After": str(exc.retry_after)})


async def _store_unavailable(request: Request, exc: StoreUnavailable) -> JSONResponse:
    # its message names the key and the kind of failure, never the endpoint
    log.warning("object store unavailable on %s: %s", request.url.path, exc)
    return _message(503, str(exc), {"Retry-After": str(exc.retry_after)}, request=request)


async def _storage(request: Request, exc: Exception) -> JSONResponse:
    """An OSError or SQLite error that reached a handler: the server's state, not the client's."""
    if is_disk_full(exc):
        log.error("disk full on %s: %s", request.url.path, exc)
        return _message(507, _DISK_FULL)
    log.exception("storage error on %s", request.url.path, exc_info=exc)
    return _message(503, "the server cannot use its storage right now; try again later",
                    {"Retry-After": "30"})


async def _broken(request: Request, exc: Exception) -> JSONResponse:
    log.error("%s on %s: %s", type(exc).__name__, request.url.path, exc)
    return _message(500, "the server could not read its stored data for this request; "
                         "the server log has the details")


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    problems = []
    for error in exc.errors():
        where = [str(part) for part in error.get("loc", ()) if part not in ("body",)]
        place = f"{where[0]} parameter {'.'.join(where[1:])!r}" if len(where) > 1 else "request"
        problems.append(f"{place}: {error.get('msg', 'invalid')}")
    return _message(422, "; ".join(problems) or "the request is invalid")


async def _http_error(request: Request, exc: HTTPException) -> JSONResponse:
    return _message(exc.status_code, str(exc.detail), getattr(exc, "headers", None),
                    request=request)


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unexpected error on %s", request.url.path, exc_info=exc)
    return _message(500, "internal server error; the server log has the details")


def add_error_handlers(app: FastAPI) -> None:
    # Starlette picks the handler of the nearest class in the exception's MRO,
    # so the 500s for broken stored data win over MeshError's 422.
    for kind in (ArtefactError, PacketError):
        app.add_exception_handler(kind, _broken)
    for kind in _STATUS:
        app.add_exception_handler(kind, _domain_error)
    app.add_exception_handler(ParserBusy, _busy)
    app.add_exception_handler(StoreUnavailable, _store_unavailable)
    for kind in (OSError, sqlite3.Error):
        app.add_exception_handler(kind, _storage)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(HTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected)
