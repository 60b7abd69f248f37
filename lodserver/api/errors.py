"""Domain errors -> HTTP status codes, in one place.

=========================  ====  ==============================================
error                      code  when
=========================  ====  ==============================================
UnknownMeshError           404   no mesh has the id (or it is malformed)
AbsentError                404   the mesh has no materials, or no such image
NotReadyError              409   the mesh is queued, building or failed
LimitError                 413   upload larger than allowed, or too many triangles
UnsupportedUpload          415   not multipart, or a file type lodserver cannot read
MeshError, LevelError      422   not a mesh / bad level parameters
RequestValidationError     422   parameters of the wrong type or range
ArtefactError, PacketError 500   a stored artefact or an encoder is broken (a bug)
=========================  ====  ==============================================

Bodies are always ``{"message": "..."}``.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException

from ..appearance import AbsentError
from ..codec import ArtefactError
from ..jobs import LimitError
from ..mesh import MeshError
from ..packets import PacketError
from ..store import NotReadyError, UnknownMeshError
from .upload import UnsupportedUpload

log = logging.getLogger(__name__)

_STATUS = {UnknownMeshError: 404, AbsentError: 404, NotReadyError: 409, LimitError: 413,
           UnsupportedUpload: 415, MeshError: 422}


def _message(status: int, message: str, headers=None) -> JSONResponse:
    return JSONResponse({"message": message}, status_code=status, headers=headers)


async def _domain_error(request: Request, exc: Exception) -> JSONResponse:
    status = next(code for kind, code in _STATUS.items() if isinstance(exc, kind))
    return _message(status, str(exc))


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
    return _message(exc.status_code, str(exc.detail), getattr(exc, "headers", None))


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
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(HTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected)
