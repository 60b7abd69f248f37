"""Dependencies routes declare in their signatures (``Annotated`` aliases)."""

from __future__ import annotations

import hmac
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from ..service.jobs import JobRunner
from ..service.parsing import RETRY_AFTER, ParserBusy
from ..service.store import ID_PATTERN, Store
from .settings import Settings, get_settings
from .upload import Upload, UploadPace, UploadSlots, receive_upload

SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_jobs(request: Request) -> JobRunner:
    return request.app.state.jobs


StoreDep = Annotated[Store, Depends(get_store)]
JobsDep = Annotated[JobRunner, Depends(get_jobs)]

_bearer = HTTPBearer(auto_error=False, description="Needed on write endpoints when the server "
                     "has LODSERVER_TOKEN set.")


def require_token(settings: SettingsDep,
                  credentials: Annotated[HTTPAuthorizationCredentials | None,
                                         Depends(_bearer)]) -> None:
    """Refuse the request (401) unless it carries the configured bearer token."""
    if settings.token is None:
        return
    expected = settings.token.get_secret_value().encode()
    given = credentials.credentials.encode() if credentials else b""
    if not hmac.compare_digest(given, expected):
        raise HTTPException(401, "this endpoint needs the header 'Authorization: Bearer <token>' "
                            "with the server's token" if credentials is None
                            else "the bearer token is wrong",
                            headers={"WWW-Authenticate": "Bearer"})


TokenDep = Annotated[None, Depends(require_token)]


async def get_upload(_: TokenDep, request: Request, settings: SettingsDep,
                     store: StoreDep, jobs: JobsDep) -> AsyncIterator[Upload]:
    """The streamed upload, removed once the request is done with it.

    The token is checked first, so no body is read without it; and when the
    parse queue is already full, or ``concurrent_uploads`` bodies are arriving,
    the upload is refused (503) before its body is read.
    """
    if jobs.parser is not None and jobs.parser.full:
        raise ParserBusy("the server is parsing as many uploads as it can; try again in "
                         f"{RETRY_AFTER} seconds")
    slots = getattr(request.app.state, "upload_slots", None)
    if slots is None:       # the first upload: on the event loop, no other can race it
        slots = request.app.state.upload_slots = UploadSlots(settings.concurrent_uploads)
    slots.take()
    try:
        upload = await receive_upload(
            request, limit=settings.max_upload_bytes, store=store, limits=settings.set_limits,
            pace=UploadPace(idle_seconds=settings.upload_idle_seconds,
                            min_rate=settings.upload_min_rate,
                            rate_seconds=settings.upload_rate_seconds))
    finally:
        slots.give_back()
    try:
        yield upload
    finally:
        # synchronous: also when the request is cancelled
        upload.discard()


UploadDep = Annotated[Upload, Depends(get_upload)]
# A malformed id is answered like an unknown one (404): the store checks every id
# against ID_PATTERN before making a path of it.
MeshId = Annotated[str, Path(description="The mesh id returned by POST /meshes "
                             f"(matches {ID_PATTERN.pattern}).")]
