"""Security headers on every response, errors, redirects and 304s included.

* ``X-Content-Type-Options: nosniff`` everywhere: a body is only ever what its
  ``Content-Type`` says (an image is never run as a page or a script).
* The viewer (``/viewer``, ``/viewer/...``): a ``Content-Security-Policy`` that
  allows only the viewer's own files, plus ``Referrer-Policy: no-referrer`` and
  ``X-Frame-Options: DENY``. The import map of ``index.html`` must stay inline
  (browsers do not load external import maps), so ``script-src`` names it by its
  SHA-256, read from the served ``index.html`` (again whenever that file
  changes). Inline ``<style>`` elements, if any are left, are named the same way;
  ``style=`` attributes and inline event handlers are refused.
* Everything else is the API, whose bodies are data, never pages:
  ``default-src 'none'; frame-ancestors 'none'``. The OpenAPI pages (``/docs``,
  ``/redoc``) load Swagger UI / ReDoc from their CDN with an inline script, so
  they get no CSP.

The middleware wraps the app's whole stack, outside Starlette's
``ServerErrorMiddleware``, so even a 500 for an unexpected exception has them.
"""

from __future__ import annotations

import base64
import hashlib
import os
import re
import threading
from html.parser import HTMLParser
from pathlib import Path

from fastapi import FastAPI
from starlette.datastructures import MutableHeaders

from .routes.viewer import MOUNT

API_CSP = "default-src 'none'; frame-ancestors 'none'"
# What static/ needs: its modules and vendored three.js, the mesh's textures
# (same origin; blob:/data: for decoded images), fetches of the API, WebGL (no
# CSP source needed), DecompressionStream (no URL).
VIEWER_CSP = ("default-src 'self'; script-src 'self'{scripts}; style-src 'self'{styles}; "
              "img-src 'self' blob: data:; connect-src 'self'; worker-src 'self' blob:; "
              "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
DOCS = ("/docs", "/redoc")


class _InlineBlocks(HTMLParser):
    """The text of each inline ``<script type="importmap">`` and ``<style>``."""

    def __init__(self):
        super().__init__(convert_charrefs=False)
        self.scripts, self.styles = [], []
        self._open = None

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "script" and (attrs.get("type") or "").strip().lower() == "importmap" \
                and "src" not in attrs:
            self._open = (self.scripts, [])
        elif tag == "style":
            self._open = (self.styles, [])

    def handle_data(self, data):
        if self._open is not None:
            self._open[1].append(data)

    def handle_endtag(self, tag):
        if self._open is not None and tag in ("script", "style"):
            into, parts = self._open
            into.append("".join(parts))
            self._open = None


def inline_hashes(html: str) -> tuple[list[str], list[str]]:
    """CSP sources (``'sha256-...'``) of the import maps and the ``<style>``
    elements of ``html``: the hash of each element's text as the browser sees
    it (line breaks normalized to LF, UTF-8)."""
    html = re.sub(r"\r\n?", "\n", html)
    parser = _InlineBlocks()
    parser.feed(html)
    parser.close()

    def source(text: str) -> str:
        digest = hashlib.sha256(text.encode("utf-8")).digest()
        return f"'sha256-{base64.b64encode(digest).decode()}'"

    return [source(t) for t in parser.scripts], [source(t) for t in parser.styles]


class ViewerPolicy:
    """The viewer's CSP, from ``index.html`` in ``folder``, re-read when it changes;
    or from the page as served, when ``page`` gives it: ``page()`` -> (html or
    None, a key that changes with it) (routes/viewer_files.py rewrites the
    page's URLs into its versioned path, the import map's included)."""

    def __init__(self, folder: Path, page=None):
        self.index = Path(folder) / "index.html"
        self.page = page
        self._lock = threading.Lock()
        self._seen, self._policy = None, VIEWER_CSP.format(scripts="", styles="")

    def policy(self) -> str:
        html = None
        if self.page is not None:
            html, seen = self.page()
            if html is None:
                return self._policy
        else:
            try:
                stat = os.stat(self.index)
                seen = (stat.st_mtime_ns, stat.st_size)
            except OSError:
                return self._policy
        with self._lock:
            if seen != self._seen:
                try:
                    scripts, styles = inline_hashes(
                        html if html is not None else self.index.read_text(encoding="utf-8"))
                except (OSError, UnicodeDecodeError):
                    scripts, styles = [], []
                self._policy = VIEWER_CSP.format(scripts="".join(f" {s}" for s in scripts),
                                                 styles="".join(f" {s}" for s in styles))
                self._seen = seen
            return self._policy


class SecurityHeaders:
    """ASGI middleware adding the headers above to every HTTP response."""

    def __init__(self, app, *, viewer: ViewerPolicy):
        self.app, self.viewer = app, viewer

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope.get("path", "")
        if path == MOUNT or path.startswith(MOUNT + "/"):
            extra = (("Content-Security-Policy", self.viewer.policy()),
                     ("Referrer-Policy", "no-referrer"), ("X-Frame-Options", "DENY"))
        elif path in DOCS or path.startswith("/docs/"):
            extra = ()
        else:
            extra = (("Content-Security-Policy", API_CSP),)

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                headers["X-Content-Type-Options"] = "nosniff"
                for name, value in extra:
                    headers[name] = value
            await send(message)

        await self.app(scope, receive, send_with_headers)


def add_security_headers(app: FastAPI, settings) -> None:
    """Wrap ``app``'s whole middleware stack (built on its first request) in
    :class:`SecurityHeaders`."""
    files = getattr(app.state, "viewer_files", None)     # routes/viewer.py mount_static
    viewer = ViewerPolicy(settings.static_dir, page=files.page if files else None)
    build = app.build_middleware_stack

    def build_with_headers():
        return SecurityHeaders(build(), viewer=viewer)

    app.build_middleware_stack = build_with_headers
