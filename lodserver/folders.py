"""The folders of the asset pipeline: a local path or an object-store prefix.

:class:`Folder` gives ``export_folder`` one face for both: listing, hashing
(objects ``STORE_READERS`` at once), the manifest, whole-object writes. A task
whose source is in an object store copies it, and the files it names (a
``.gltf``'s buffers and images, an OBJ's ``mtllib`` files and their texture
maps, only inside the source prefix), into a local folder first
(:func:`fetch_with_references`). Object-store errors (botocore's) become
``OSError``, what a folder that cannot be read raises here.
"""

from __future__ import annotations

import hashlib
import json
import posixpath
import re
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from urllib.parse import unquote

from .io import write_atomic
from .mesh import MeshError

MANIFEST = "lodserver-export.json"
# 2: glTF sources export their scene (io/scene_glb.py), not one flattened mesh.
MANIFEST_VERSION = 2
# Objects hashed at once: each GET waits mostly on the store's latency.
STORE_READERS = 16


def is_url(location) -> bool:
    """Whether ``location`` names an object-store folder (``s3://bucket/prefix``), not a path."""
    return isinstance(location, str) and _URL.match(location) is not None


_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]+://")


class Folder:
    """A folder of the pipeline: a local path, or an object-store prefix through fsspec."""

    def __init__(self, location):
        self.remote = is_url(location)
        if self.remote:
            self.url = location.rstrip("/")
            self.fs, self.root = filesystem(self.url)
        else:
            self.path = Path(location)

    def shared(self, absolute: bool) -> str:
        """The folder as a task gets it: the URL, or the path (absolute if asked)."""
        if self.remote:
            return self.url
        return str(self.path.absolute() if absolute else self.path)

    def is_folder(self) -> bool:
        return self.fs.isdir(self.root) if self.remote else self.path.is_dir()

    def create(self) -> None:
        # an object store has no folders: a key's prefix exists once a key does
        if not self.remote:
            self.path.mkdir(parents=True, exist_ok=True)

    def location(self, relative):
        """Where ``relative`` is, as the caller named the folder (a Path or a URL)."""
        if self.remote:
            return f"{self.url}/{PurePosixPath(relative)}"
        return self.path.joinpath(*PurePosixPath(relative).parts)

    def existing(self):
        """An object answering ``name in existing``: is ``output/name`` a file."""
        if not self.remote:
            return _LocalFiles(self.path)
        return {key[len(self.root) + 1:] for key in listing(self.fs, self.root)}

    def sha256_all(self, relatives: list) -> dict:
        """``{relative: SHA-256 hex digest, or the OSError reading it raised}``.

        Local files are read one after the other, as ever; objects
        ``STORE_READERS`` at once, since each GET waits mostly on the store's
        latency, and this pass runs before any task starts.
        """
        def digest(relative):
            try:
                return self.sha256(relative)
            except OSError as exc:
                return exc

        if not self.remote:
            return {relative: digest(relative) for relative in relatives}
        with ThreadPoolExecutor(max_workers=STORE_READERS) as pool:
            return dict(zip(relatives, pool.map(digest, relatives)))

    def sha256(self, relative) -> str:
        if not self.remote:
            return _sha256(self.path / relative)
        with _store_errors(), self.fs.open(f"{self.root}/{PurePosixPath(relative)}",
                                           "rb") as file:
            return _sha256_of(file)

    def read_manifest(self) -> dict:
        """The sources recorded by an earlier run; empty when there is none or it is
        unreadable (then everything is rebuilt, which is always safe)."""
        try:
            if self.remote:
                text = self.fs.cat_file(f"{self.root}/{MANIFEST}")
            else:
                text = (self.path / MANIFEST).read_bytes()
            document = json.loads(text)
        except (OSError, ValueError):
            return {}
        if not isinstance(document, dict) or document.get("version") != MANIFEST_VERSION:
            return {}
        sources = document.get("sources")
        return dict(sources) if isinstance(sources, dict) else {}

    def write(self, name: str, data: bytes) -> None:
        if self.remote:
            self.fs.pipe_file(f"{self.root}/{name}", data)     # one PUT: whole or not at all
        else:
            write_atomic(self.path / name, data)


class _LocalFiles:
    def __init__(self, folder: Path):
        self.folder = folder

    def __contains__(self, name) -> bool:
        return (self.folder / name).is_file()


def filesystem(url: str):
    """``(filesystem, root)`` for an object-store URL; root without the scheme or a
    trailing slash. A fresh instance: fsspec's cache would keep a client made for
    other AWS_* settings."""
    try:
        import fsspec
        fs, root = fsspec.core.url_to_fs(url, skip_instance_cache=True)
    except ImportError as exc:
        raise MeshError(f"object-store folders such as {url} need the distributed extra "
                        f"(pip install 'lodserver[distributed]'): {exc}") from None
    except ValueError as exc:
        raise MeshError(f"cannot use {url}: {exc}") from None
    return _Store(fs), root.rstrip("/")


class _Store:
    """An fsspec filesystem whose calls raise OSError for the object store's own errors
    (botocore's: no credentials, no endpoint, ...), which name no Python type the
    callers know; ``OSError`` is what a folder that cannot be read raises here."""

    def __init__(self, fs):
        self._fs = fs

    def __getattr__(self, name):
        attribute = getattr(self._fs, name)
        if not callable(attribute):
            return attribute

        def call(*args, **kwargs):
            with _store_errors():
                return attribute(*args, **kwargs)
        return call


@contextmanager
def _store_errors():
    try:
        yield
    except OSError:
        raise
    except Exception as exc:
        if not type(exc).__module__.startswith(("botocore", "aiobotocore", "s3fs", "fsspec")):
            raise
        raise OSError(f"the object store failed: {exc}") from None


def listing(fs, root: str) -> list[str]:
    """Every key under ``root`` (none when it does not exist)."""
    try:
        return sorted(fs.find(root))
    except FileNotFoundError:
        return []


# The keywords of MTL lines that name a texture file (the name is the line's tail,
# after options whose count varies, so every tail is tried).
_MTL_MAPS = re.compile(rb"(?m)^[ \t]*(?:map_\w+|bump|disp|decal|refl|norm)[ \t]+(.+?)[ \t]*\r?$")
_MTLLIB = re.compile(rb"(?m)^[ \t]*mtllib[ \t]+(.+?)[ \t]*\r?$")
# a file naming more than this many files is not fetched past them
_MAX_REFERENCES = 256


def fetch_with_references(fs, root: str, relative: PurePosixPath, into: Path) -> Path:
    """Copy ``root/relative`` and the files it names into ``into`` (same layout).

    What is named: a ``.gltf``'s buffer and image URIs, an OBJ's ``mtllib``
    files and their texture maps. Only names that resolve inside ``root`` and
    exist there are fetched; the loader then judges the copy exactly as it would
    the original (a missing texture is its error, not ours). Returns the local
    copy of the source.
    """
    fetched: set[PurePosixPath] = set()
    pending = [relative]
    while pending and len(fetched) <= _MAX_REFERENCES:
        name = pending.pop()
        if name in fetched:
            continue
        key = f"{root}/{name}"
        if name != relative and not fs.isfile(key):
            continue
        local = into.joinpath(*name.parts)
        local.parent.mkdir(parents=True, exist_ok=True)
        fs.get_file(key, str(local))
        fetched.add(name)
        for reference in _named_files(local.read_bytes(), name.suffix.lower()):
            resolved = _inside(name.parent, reference)
            if resolved is not None:
                pending.append(resolved)
    return into.joinpath(*relative.parts)


def _named_files(data: bytes, suffix: str) -> list[str]:
    """The file names a ``.gltf``, ``.obj`` or ``.mtl`` file's bytes may refer to
    (candidates: an MTL line's every tail, an ``mtllib`` line whole and word by word)."""
    if suffix == ".gltf":
        try:
            document = json.loads(data)
        except ValueError:
            return []
        records = [record for kind in ("buffers", "images")
                   for record in (document.get(kind) or []) if isinstance(record, dict)]
        return [unquote(record["uri"]) for record in records
                if isinstance(record.get("uri"), str) and not record["uri"].startswith("data:")]
    pattern = {".obj": _MTLLIB, ".mtl": _MTL_MAPS}.get(suffix)
    if pattern is None:
        return []
    names = []
    for match in pattern.finditer(data):
        words = match.group(1).decode("utf-8", errors="replace").split()
        if suffix == ".obj":
            names += [" ".join(words)] + words
        else:
            names += [" ".join(words[at:]) for at in range(len(words))]
    return names


def _inside(folder: PurePosixPath, name: str) -> PurePosixPath | None:
    """``name`` relative to ``folder``, normalised; None if absolute or above the root."""
    name = name.replace("\\", "/")
    if not name or name.startswith("/") or _URL.match(name):
        return None
    joined = posixpath.normpath(posixpath.join(str(folder), name))
    if joined == ".." or joined.startswith("../") or joined.startswith("/"):
        return None
    return PurePosixPath(joined)


def _sha256(path: Path) -> str:
    with open(path, "rb") as file:
        return _sha256_of(file)


def _sha256_of(file) -> str:
    digest = hashlib.sha256()
    for block in iter(lambda: file.read(1 << 20), b""):
        digest.update(block)
    return digest.hexdigest()
