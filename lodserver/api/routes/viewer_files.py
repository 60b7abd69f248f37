"""The viewer's files as a browser should get them: versioned, compressed, cached.

``ViewerFiles(folder)`` reads every file of the viewer's folder into memory
once (a few MB, most of it three.js), with its SHA-256 and, for text types worth
it, a gzip body made at start (level 9: done once, so the slowest level costs
nothing per request). The folder's *version* is a digest of all its files'
paths and contents. Then:

* ``/viewer/v/<version>/<path>``: the file, ``Cache-Control: public,
  max-age=31536000, immutable``: a URL whose content never changes.
* ``/viewer/`` (``index.html``): ``no-cache`` (revalidated by its ETag each
  load), its quoted ``./`` URLs, the import map's included, pointing into
  ``./v/<version>/``. Relative module imports then resolve inside the
  versioned path, while the page keeps its URL (its ``../meshes`` fetches
  and ``?mesh=`` links resolve as from ``/viewer/``). The CSP's import-map hash is computed
  from this served page (``headers.ViewerPolicy``).
* ``/viewer/<path>``: the current file, unversioned, ``no-cache`` with an ETag
  (for old links and for pages that import a module by its plain path).

Every body has a strong ETag (its content's hash; the gzip body its own,
``-gz`` suffixed, since its bytes differ), honours ``If-None-Match`` with a
304, and names ``Vary: Accept-Encoding`` when a gzip form exists. Only files
read at the scan are served, so no request path reaches the file system.

Edits to the folder (a checkout being worked on) are picked up: the page
request checks the files' sizes and modification times (a stat each, about
30 files) and rescans when one changed; the last few versions stay served,
so a page loaded just before an edit still gets its own files.
"""

from __future__ import annotations

import gzip
import hashlib
import logging
import mimetypes
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

IMMUTABLE = "public, max-age=31536000, immutable"
REVALIDATE = "no-cache"
# Types worth compressing (images and fonts are compressed already).
COMPRESSIBLE = (".js", ".mjs", ".css", ".html", ".json", ".svg", ".txt", ".map", ".md")
MIN_GZIP_BYTES = 1024
KEPT_VERSIONS = 3
VERSION_CHARS = 16                  # hex digits of the folder digest in URLs
MEDIA_TYPES = {".js": "text/javascript; charset=utf-8", ".mjs": "text/javascript; charset=utf-8",
               ".css": "text/css; charset=utf-8", ".html": "text/html; charset=utf-8",
               ".json": "application/json", ".svg": "image/svg+xml", ".wasm": "application/wasm"}
# A quoted URL starting "./" in the page: attributes and the import map's values.
_RELATIVE = re.compile(r"""(["'])\./""")


@dataclass(frozen=True)
class Body:
    """One file: its bytes, its gzip bytes (or None), media type and ETags."""
    data: bytes
    gzipped: bytes | None
    media_type: str
    etag: str
    gzip_etag: str | None


def make_body(data: bytes, name: str) -> Body:
    """The :class:`Body` of ``data`` named ``name`` (its suffix picks the type
    and whether to compress)."""
    suffix = Path(name).suffix.lower()
    media = MEDIA_TYPES.get(suffix) or mimetypes.guess_type(name)[0] or "application/octet-stream"
    digest = hashlib.sha256(data).hexdigest()[:32]
    packed = None
    if suffix in COMPRESSIBLE and len(data) >= MIN_GZIP_BYTES:
        # mtime=0: the same bytes on every start, so the gzip ETag is stable too
        packed = gzip.compress(data, compresslevel=9, mtime=0)
        if len(packed) >= len(data):
            packed = None
    return Body(data, packed, media, f'"{digest}"', f'"{digest}-gz"' if packed else None)


def _listing(folder: Path) -> dict[str, tuple[int, int]]:
    """(size, mtime_ns) of each regular file under folder, by POSIX relative path;
    hidden files and folders and ``__pycache__`` left out, symlinks not followed."""
    found = {}
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and d != "__pycache__")
        for name in files:
            if name.startswith("."):
                continue
            path = Path(root) / name
            try:
                stat = path.lstat()
            except OSError:
                continue
            if path.is_symlink() or not path.is_file():
                continue
            found[path.relative_to(folder).as_posix()] = (stat.st_size, stat.st_mtime_ns)
    return found


@dataclass(frozen=True)
class Version:
    """One scan of the folder: its files' bodies, the page, and its version."""
    name: str
    files: dict[str, Body]
    page: Body | None           # index.html as served (pointing into this version)
    page_text: str | None
    listing: dict[str, tuple[int, int]]


def rewrite_page(html: str, version: str) -> str:
    """``html`` with each quoted URL starting ``./`` moved under ``./v/<version>/``."""
    return _RELATIVE.sub(lambda m: f"{m.group(1)}./v/{version}/", html)


def scan(folder: Path) -> Version:
    """Read the folder into a :class:`Version`."""
    listing = _listing(folder)
    files, summary = {}, hashlib.sha256()
    for name in sorted(listing):
        try:
            data = (folder / name).read_bytes()
        except OSError:
            continue
        body = make_body(data, name)
        files[name] = body
        summary.update(name.encode() + b"\0" + body.etag.encode() + b"\0")
    name = summary.hexdigest()[:VERSION_CHARS]
    page = page_text = None
    if "index.html" in files:
        try:
            page_text = rewrite_page(files["index.html"].data.decode("utf-8"), name)
            page = make_body(page_text.encode("utf-8"), "index.html")
        except UnicodeDecodeError:
            log.warning("the viewer's index.html is not UTF-8; served as it is")
            page = files["index.html"]
    return Version(name, files, page, page_text, listing)


class ViewerFiles:
    """The viewer's folder, scanned, rescanned when it changes (see the module doc)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self._lock = threading.Lock()
        self._versions: list[Version] = [scan(self.folder)]
        log.info("viewer files: version %s, %d files", self.current.name,
                 len(self.current.files))

    @property
    def current(self) -> Version:
        return self._versions[-1]

    def refresh(self) -> Version:
        """The current version, rescanning first if a file changed."""
        with self._lock:
            if _listing(self.folder) != self.current.listing:
                fresh = scan(self.folder)
                if fresh.name != self.current.name:
                    self._versions = [*self._versions, fresh][-KEPT_VERSIONS:]
                else:    # touched, same content: keep the version, note the new times
                    self._versions[-1] = fresh
            return self.current

    def version(self, name: str) -> Version | None:
        """A version still served, by name."""
        return next((v for v in reversed(self._versions) if v.name == name), None)

    def page(self) -> tuple[str | None, str]:
        """(index.html as served, a key that changes with it), for the CSP."""
        current = self.refresh()
        return current.page_text, current.name
