"""The browser viewer (``static/`` in the repository): ``/viewer/`` serves it,
``/`` and ``/viewer`` lead there (keeping ``?mesh=ID``).

Its files are served from memory, versioned, gzip-compressed and cached
(``viewer_files.py``): the page ``no-cache``, pointing at
``/viewer/v/<version>/``, whose files are immutable for a year.

The files are found in ``Settings.static_dir`` (``LODSERVER_STATIC_DIR``; by
default the checkout's ``static/``). Without them the API still runs and
``/viewer`` answers 404 naming the setting (the folder it looked in goes to the
log, not to the client).
"""

from __future__ import annotations

import logging
import re

from fastapi import APIRouter, FastAPI, HTTPException, Request
from fastapi.responses import RedirectResponse, Response

from ..deps import SettingsDep
from .viewer_files import IMMUTABLE, REVALIDATE, Body, ViewerFiles

log = logging.getLogger(__name__)

router = APIRouter(tags=["viewer"], include_in_schema=False)

MOUNT = "/viewer"


def _to_viewer(request: Request) -> RedirectResponse:
    # Relative ("viewer/" from "/" and from "/viewer" alike), so the redirect
    # also works behind a proxy that adds a path prefix.
    query = f"?{request.url.query}" if request.url.query else ""
    return RedirectResponse(f"viewer/{query}")


@router.get("/")
def root(request: Request) -> RedirectResponse:
    return _to_viewer(request)


@router.get(MOUNT)
def viewer(request: Request, settings: SettingsDep) -> RedirectResponse:
    """``/viewer`` -> ``/viewer/``: the page's relative URLs resolve under the slash."""
    if not (settings.static_dir / "index.html").is_file():
        log.warning("the viewer's files are not installed: no index.html in %s",
                    settings.static_dir)
        raise HTTPException(404, "the viewer's files are not installed on this server; "
                            "LODSERVER_STATIC_DIR must name the folder holding its index.html")
    return _to_viewer(request)


def accepts_gzip(request: Request) -> bool:
    """Whether the request's Accept-Encoding takes gzip (not at q=0)."""
    for part in request.headers.get("accept-encoding", "").split(","):
        coding, _, params = part.strip().partition(";")
        if coding.strip().lower() in ("gzip", "*"):
            quality = params.strip().lower()
            return not re.fullmatch(r"q\s*=\s*0(\.0*)?", quality)
    return False


def _matches(request: Request, etag: str) -> bool:
    wanted = request.headers.get("if-none-match")
    if not wanted:
        return False
    tags = [t.strip().removeprefix("W/") for t in wanted.split(",")]
    return "*" in tags or etag in tags


def file_response(request: Request, body: Body, cache_control: str) -> Response:
    """``body`` (gzipped when the client takes it) with its ETag and
    ``cache_control``; a 304 when the client holds it already."""
    packed = body.gzipped is not None and accepts_gzip(request)
    etag = body.gzip_etag if packed else body.etag
    headers = {"ETag": etag, "Cache-Control": cache_control}
    if body.gzipped is not None:
        headers["Vary"] = "Accept-Encoding"
    if _matches(request, etag):
        return Response(status_code=304, headers=headers)
    if packed:
        headers["Content-Encoding"] = "gzip"
    return Response(body.gzipped if packed else body.data, media_type=body.media_type,
                    headers=headers)


def _missing(what: str) -> HTTPException:
    return HTTPException(404, what)


def files_router(files: ViewerFiles) -> APIRouter:
    """The routes serving ``files`` under ``/viewer/``."""
    served = APIRouter(tags=["viewer"], include_in_schema=False)

    @served.api_route(MOUNT + "/", methods=["GET", "HEAD"])
    @served.api_route(MOUNT + "/index.html", methods=["GET", "HEAD"])
    def page(request: Request) -> Response:
        current = files.refresh()
        if current.page is None:
            raise _missing("the viewer's page is not installed on this server")
        return file_response(request, current.page, REVALIDATE)

    @served.api_route(MOUNT + "/v/{version}/{path:path}", methods=["GET", "HEAD"])
    def versioned(version: str, path: str, request: Request) -> Response:
        found = files.version(version) or (files.refresh().name == version and files.current)
        if not found:
            raise _missing("this version of the viewer is no longer served; reload the page")
        body = found.files.get(path)
        if body is None:
            raise _missing("the viewer has no such file")
        return file_response(request, body, IMMUTABLE)

    @served.api_route(MOUNT + "/{path:path}", methods=["GET", "HEAD"])
    def plain(path: str, request: Request) -> Response:
        body = files.refresh().files.get(path)
        if body is None:
            raise _missing("the viewer has no such file")
        return file_response(request, body, REVALIDATE)

    return served


def mount_static(app: FastAPI, settings) -> None:
    """Serve the viewer's files under ``/viewer/`` when they are there
    (``app.state.viewer_files``, whose served page the CSP hashes)."""
    folder = settings.static_dir
    app.state.viewer_files = None
    if (folder / "index.html").is_file():
        app.state.viewer_files = ViewerFiles(folder)
        app.include_router(files_router(app.state.viewer_files))
