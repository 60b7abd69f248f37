"""The browser viewer (``static/`` in the repository): ``/viewer/`` serves it,
``/`` and ``/viewer`` lead there (keeping ``?mesh=ID``).

The files are found in ``Settings.static_dir`` (``LODSERVER_STATIC_DIR``; by
default the checkout's ``static/``). Without them the API still runs and
``/viewer`` answers 404 naming the setting (the folder it looked in goes to the
log, not to the client).
"""

from __future__ import annotations

import logging

from fastapi import APIRouter, FastAPI, HTTPException, Request
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles

from ..deps import SettingsDep

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


def mount_static(app: FastAPI, settings) -> None:
    """Serve the viewer's files under ``/viewer/`` when they are there."""
    folder = settings.static_dir
    if (folder / "index.html").is_file():
        app.mount(MOUNT, StaticFiles(directory=folder, html=True), name="viewer")
