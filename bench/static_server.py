"""A quiet HTTP server of a folder on loopback, for the benchmarks that drive a
headless browser over the repository's files (``render/render.py``,
``scenes/judge.py``): the vendored three.js as JavaScript modules and GLB
files with glTF's own media type."""

from __future__ import annotations

import contextlib
import functools
import http.server
import threading
from pathlib import Path

# Module scripts must come as JavaScript; the rest as glTF and JSON say.
TYPES = {".js": "text/javascript", ".mjs": "text/javascript",
         ".glb": "model/gltf-binary", ".json": "application/json"}


@contextlib.contextmanager
def serve(directory: Path):
    """Serve ``directory`` on 127.0.0.1 at an ephemeral port while the block runs;
    yields the base URL (``http://127.0.0.1:<port>``)."""

    class Handler(http.server.SimpleHTTPRequestHandler):
        extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, **TYPES}

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(
        ("127.0.0.1", 0), functools.partial(Handler, directory=str(directory)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
