"""A quiet HTTP server of a folder on loopback, for the benchmarks that drive a
headless browser over the repository's files (``render/render.py``,
``scenes/judge.py``): the vendored three.js as JavaScript modules and GLB
files with glTF's own media type."""

from __future__ import annotations

import contextlib
import functools
import gzip
import http.server
import re
import threading
from pathlib import Path

# Module scripts must come as JavaScript; the rest as glTF and JSON say.
TYPES = {".js": "text/javascript", ".mjs": "text/javascript",
         ".glb": "model/gltf-binary", ".json": "application/json"}


@contextlib.contextmanager
def serve(directory: Path, log: list | None = None, gzipped: tuple = ()):
    """Serve ``directory`` on 127.0.0.1 at an ephemeral port while the block runs;
    yields the base URL (``http://127.0.0.1:<port>``). With ``log`` (a list), a
    ``Range`` request of one range of a file is answered 206 with those bytes, as
    a CDN does, and every GET is logged: ``(path, Range header, status, bytes)``.
    The request paths in ``gzipped`` are sent whole with ``Content-Encoding:
    gzip`` (compressed once, at level 9), as a CDN sends a compressible file."""
    compressed: dict = {}

    class Handler(http.server.SimpleHTTPRequestHandler):
        extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, **TYPES}

        def log_message(self, *args):
            pass

        def do_GET(self):
            asked = self.headers.get("Range") if log is not None else None
            path = Path(self.translate_path(self.path))
            if self.path in gzipped and path.is_file():
                return self.send_gzipped(path)
            match = re.fullmatch(r"bytes=(\d+)-(\d*)", asked or "")
            if not match or not path.is_file() or int(match[1]) >= path.stat().st_size:
                if log is not None:
                    log.append((self.path, asked, 200, path.stat().st_size
                                if path.is_file() else 0))
                return super().do_GET()
            data = path.read_bytes()
            stop = min(len(data), int(match[2]) + 1 if match[2] else len(data))
            body = data[int(match[1]):stop]
            log.append((self.path, asked, 206, len(body)))
            self.send_response(206)
            self.send_header("Content-Type", self.guess_type(str(path)))
            self.send_header("Content-Range", f"bytes {match[1]}-{stop - 1}/{len(data)}")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def send_gzipped(self, path: Path):
            if path not in compressed:
                compressed[path] = gzip.compress(path.read_bytes(), 9)
            body = compressed[path]
            if log is not None:
                log.append((self.path, None, 200, len(body)))
            self.send_response(200)
            self.send_header("Content-Type", self.guess_type(str(path)))
            self.send_header("Content-Encoding", "gzip")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

    server = http.server.ThreadingHTTPServer(
        ("127.0.0.1", 0), functools.partial(Handler, directory=str(directory)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
