"""Where bytes live: a local folder or an object store, behind one small interface.

:func:`open_blobs` takes the store URL (``LODSERVER_STORE_URL``): a plain path or
``file://`` URL gives :class:`LocalBlobs` (the embedded default, a folder of the
data directory), ``s3://bucket/prefix`` an S3-compatible object store through
fsspec and s3fs (:class:`FsspecBlobs`), with the endpoint and credentials taken
from the standard AWS environment variables (``AWS_ENDPOINT_URL``,
``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_DEFAULT_REGION``).
Any other fsspec URL (``memory://``, say) works the same way.

A *key* names an object relative to the store's root: ``/``-separated segments
of letters, digits, ``.``, ``_`` and ``-``, none starting with ``.`` (names
starting with a dot are this module's temporary files) and none ``..``; at
most :data:`MAX_KEY` characters. Anything else is a :class:`BlobKeyError`
before the store is touched.

Writes are atomic for readers: a local object is written under a temporary
name beside its key, flushed and renamed; an S3 PUT (single or multipart, as
fsspec chooses by size) makes the object visible only once it is complete. So
no reader, on this machine or another, ever sees half an object.

Errors are :class:`~lodserver.service.errors.StoreError` subclasses whose
message is one sentence naming the key, never a server path or endpoint:
:class:`BlobNotFoundError` for a missing object, :class:`StorageFullError`
when the local disk is full, :class:`StoreUnavailable` for an object store
that cannot be reached (refused, reset, timed out), :class:`StoreError` for
one that refuses.

Every object-store call is bounded: botocore's connection and read timeouts
(:data:`CONNECT_SECONDS`, :data:`READ_SECONDS`) and few retries, botocore's
and s3fs's own, and a write's whole deadline (:data:`CALL_SECONDS` and
:data:`MIN_BYTES_PER_SECOND`), so a store that stops answering or reading is
a :class:`StoreUnavailable` within about a minute at worst (more for a large
body) rather than a request that hangs past its client's patience.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import logging
import os
import re
import stat
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO
from urllib.parse import urlsplit

from ..io.files import CHUNK, copy_atomic, temporary_beside, write_atomic
from .errors import StorageFullError, StoreError, StoreUnavailable, is_disk_full

log = logging.getLogger(__name__)

MAX_KEY = 512
_SEGMENT = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")
# s3fs's own default part size: 50 MiB parts, for files of 100 MiB and more.
PART_BYTES = 50 * 2**20
# Object-store timeouts (seconds). botocore's defaults are 60 s each with up to
# five attempts, and s3fs retries five times more over them: a store that
# stalls would hold a request for many minutes. A connection on a working
# network opens far within CONNECT_SECONDS; READ_SECONDS is the wait for any
# byte of an answer (not for a whole body), long enough for a loaded store
# to assemble a large multipart upload.
CONNECT_SECONDS = 5.0
READ_SECONDS = 15.0
# Attempts per call: botocore's (its "standard" mode backs off between them),
# which ride out one dropped connection, and s3fs's loop over those (1: none of
# its own, which would multiply the wait on a store that stalls).
BOTO_ATTEMPTS = 2
S3FS_RETRIES = 1
# A write's whole deadline (seconds), over those timeouts: they bound each wait
# for an answer, never the sending of a body, so a store that stops reading
# mid-upload would hold a put, and the build or request behind it, for ever.
# Generous, so that a body sent at MIN_BYTES_PER_SECOND still goes up.
CALL_SECONDS = 60.0
MIN_BYTES_PER_SECOND = 2**20


class BlobKeyError(StoreError, ValueError):
    """A key that is not a plain relative name (module docstring)."""


class BlobNotFoundError(StoreError, FileNotFoundError):
    """No object is stored under the key."""

    def __init__(self, key: str):
        super().__init__(f"no stored object has the key {key!r}")
        self.key = key


def check_key(key: str) -> str:
    """``key`` if it is a valid key (module docstring), else :class:`BlobKeyError`."""
    if not isinstance(key, str) or not key or len(key) > MAX_KEY:
        raise BlobKeyError(f"a key is a non-empty string of at most {MAX_KEY} characters")
    segments = key.split("/")
    if not all(_SEGMENT.fullmatch(segment) for segment in segments):
        raise BlobKeyError(f"the key {key[:64]!r} is not a relative name of plain segments "
                           "(letters, digits, '.', '_', '-'; none starting with '.')")
    return key


def sha256_file(path) -> str:
    """The SHA-256 of a file's bytes (hex, 64 characters), read in pieces."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        while piece := file.read(CHUNK):
            digest.update(piece)
    return digest.hexdigest()


class Blobs(ABC):
    """Objects by key (module docstring). Safe to use from several threads."""

    url: str

    @abstractmethod
    def put_file(self, key: str, path, *, move: bool = False) -> None:
        """Store the file at ``path`` under ``key``, replacing any object there,
        atomically for readers. ``move=True`` lets the store take the file (a rename
        when it can): once stored, it is gone from ``path``."""

    @abstractmethod
    def put_bytes(self, key: str, data) -> None:
        """Store ``data`` (bytes-like) under ``key``, atomically for readers."""

    @abstractmethod
    def open(self, key: str) -> BinaryIO:
        """A binary file object reading the object; the caller closes it."""

    @abstractmethod
    def get_file(self, key: str, dest) -> None:
        """Copy the object to the local file ``dest`` (written under a temporary
        name and renamed, so ``dest`` is never partial)."""

    @abstractmethod
    def exists(self, key: str) -> bool: ...

    @abstractmethod
    def size(self, key: str) -> int:
        """The object's size in bytes."""

    @abstractmethod
    def delete(self, key: str) -> None:
        """Remove the object; nothing happens if there is none."""

    @abstractmethod
    def keys(self, prefix: str = "") -> Iterator[str]:
        """The keys under ``prefix`` (a key's leading segments, or ''), in no order."""

    @abstractmethod
    def ping(self, *, timeout: float) -> None:
        """Return once the store's root can be used, within about ``timeout`` seconds;
        else a :class:`StoreError`. The readiness probe: one cheap call (a folder's
        stat, an object store's HEAD of its bucket)."""

    def local_path(self, key: str) -> Path | None:
        """The object's own file when the store is a local folder (read it, never
        write it), else None: the caller then fetches a copy (``get_file``)."""
        return None

    def get_bytes(self, key: str) -> bytes:
        with self.open(key) as file:
            return file.read()


def delete_patiently(blobs: Blobs, key: str, *, patience: float) -> bool:
    """Delete ``key``, trying again while the store is unreachable for up to
    ``patience`` seconds (an object a row no longer names, which no later step
    would remove); False, logged, if it is still there."""
    deadline, pause = time.monotonic() + patience, 0.5
    while True:
        try:
            blobs.delete(key)
            return True
        except StoreUnavailable as exc:
            if time.monotonic() + pause > deadline:
                log.warning("the object %s could not be deleted: %s", key, exc)
                return False
            time.sleep(pause)
            pause = min(2 * pause, 5.0)


def delete_later(blobs: Blobs, key: str, *, patience: float = 300.0) -> None:
    """:func:`delete_patiently` in a thread of its own: an object whose PUT failed
    (the store cut off mid-answer) may exist all the same, and no row will ever
    name it; the request that stored it does not wait for the store to return."""
    threading.Thread(target=delete_patiently, args=(blobs, key), name="delete-later",
                     kwargs={"patience": patience}, daemon=True).start()


def open_blobs(url_or_path) -> Blobs:
    """The store named by ``url_or_path``: a local folder (a path or ``file://``
    URL; created if absent) or an fsspec URL such as ``s3://bucket/prefix``."""
    text = str(url_or_path)
    scheme = urlsplit(text).scheme if "://" in text else ""
    if scheme in ("", "file"):
        return LocalBlobs(text[len("file://"):] if scheme == "file" else text)
    return FsspecBlobs(text)


# ---- a local folder ---------------------------------------------------------------

class LocalBlobs(Blobs):
    """Objects as files under a folder, a key's segments as sub-folders."""

    def __init__(self, root):
        self.root = Path(root).absolute()
        self.url = self.root.as_uri()
        self.root.mkdir(parents=True, exist_ok=True)

    def _path(self, key: str) -> Path:
        return self.root.joinpath(*check_key(key).split("/"))

    def _writable(self, key: str) -> Path:
        path = self._path(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def put_file(self, key: str, path, *, move: bool = False) -> None:
        with _local_errors(key, "storing"):
            target = self._writable(key)
            if move:
                try:
                    # same file system: flushed (as a copy would be), then a
                    # rename, atomic and without copying
                    with open(path, "rb") as file:
                        os.fsync(file.fileno())
                    os.replace(path, target)
                    return
                except OSError as exc:
                    if exc.errno != errno.EXDEV:     # another file system: copy
                        raise
            copy_atomic(path, target)
            if move:
                Path(path).unlink(missing_ok=True)

    def put_bytes(self, key: str, data) -> None:
        with _local_errors(key, "storing"):
            write_atomic(self._writable(key), data)

    def open(self, key: str) -> BinaryIO:
        with _local_errors(key, "reading"):
            return open(self._path(key), "rb")

    def get_file(self, key: str, dest) -> None:
        with _local_errors(key, "copying"):
            copy_atomic(self._path(key), dest)

    def exists(self, key: str) -> bool:
        return self._path(key).is_file()

    def size(self, key: str) -> int:
        with _local_errors(key, "reading"):
            return self._path(key).stat().st_size

    def delete(self, key: str) -> None:
        with _local_errors(key, "deleting"):
            self._path(key).unlink(missing_ok=True)

    def keys(self, prefix: str = "") -> Iterator[str]:
        base = self._path(prefix) if prefix else self.root
        for folder, _, files in os.walk(base):
            relative = Path(folder).relative_to(self.root).parts
            for name in files:
                if not name.startswith("."):
                    yield "/".join((*relative, name))

    def local_path(self, key: str) -> Path | None:
        path = self._path(key)
        return path if path.is_file() else None

    def ping(self, *, timeout: float) -> None:
        # a folder answers at once or hangs (a lost network mount): the caller
        # bounds the wait, there is nothing to pass the timeout to
        try:
            if not stat.S_ISDIR(os.stat(self.root).st_mode):
                raise StoreError("the store's folder is not a folder")
        except OSError as exc:
            raise StoreError(f"the store's folder cannot be used: "
                             f"{exc.strerror or type(exc).__name__}") from None
        if not os.access(self.root, os.W_OK | os.X_OK):
            raise StoreError("the store's folder is not writable")


@contextlib.contextmanager
def _local_errors(key: str, doing: str) -> Iterator[None]:
    """An OSError of the block as the :class:`StoreError` of :func:`_local_error`."""
    try:
        yield
    except OSError as exc:
        raise _local_error(exc, key, doing) from exc


def _local_error(exc: OSError, key: str, doing: str) -> StoreError:
    """One sentence, no path: missing, disk full, or the OS's reason."""
    if isinstance(exc, FileNotFoundError) and doing != "storing":
        return BlobNotFoundError(key)
    if is_disk_full(exc):
        return StorageFullError(f"the server ran out of disk space while {doing} {key!r}; "
                                "try again once space is freed")
    return StoreError(f"the store failed while {doing} {key!r}: "
                      f"{exc.strerror or type(exc).__name__}")


# ---- an object store through fsspec -----------------------------------------------

def s3_options() -> dict:
    """s3fs options from the standard AWS variables. The endpoint is passed
    explicitly (``AWS_ENDPOINT_URL_S3`` or ``AWS_ENDPOINT_URL``) so that fsspec's
    cache of file-system instances keeps one per endpoint; listings are not cached,
    because other servers write to the same bucket."""
    options = {"use_listings_cache": False,
               "config_kwargs": {"connect_timeout": CONNECT_SECONDS,
                                 "read_timeout": READ_SECONDS,
                                 "retries": {"total_max_attempts": BOTO_ATTEMPTS,
                                             "mode": "standard"}}}
    endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
    if endpoint:
        options["endpoint_url"] = endpoint
    return options


class FsspecBlobs(Blobs):
    """Objects under ``protocol://root`` of an fsspec file system (S3 through s3fs).

    Parameters
    ----------
    url : str
        ``s3://bucket/prefix`` (the prefix may be empty), or another fsspec URL.
    check : bool
        Make sure the root's bucket exists now, so a wrong URL fails at start with
        a :class:`StoreError` rather than at the first upload.
    part_bytes : int
        S3 only: a file of at least twice this many bytes goes up as a multipart
        upload of parts this size (S3's smallest part is 5 MiB); a smaller one is
        one PUT, read into memory whole (s3fs).
    fs_options
        More options of the fsspec file system (s3fs: ``config_kwargs=`` for
        botocore's timeouts and retries...), over those of :func:`s3_options`.
    """

    def __init__(self, url: str, *, check: bool = True, part_bytes: int = PART_BYTES,
                 **fs_options):
        import fsspec

        protocol, _, rest = url.partition("://")
        self.url = f"{protocol}://{rest.strip('/')}"
        try:
            defaults = s3_options() if protocol in ("s3", "s3a") else {}
            self.fs = fsspec.filesystem(protocol, **{**defaults, **fs_options})
        except (ImportError, ValueError) as exc:
            raise StoreError(f"the store URL scheme {protocol!r} is not available "
                             f"({exc}); for s3:// install lodserver[distributed]") from None
        self.root = rest.strip("/")
        self._s3 = protocol in ("s3", "s3a")
        if self._s3:
            self.fs.retries = S3FS_RETRIES     # s3fs's own loop, over botocore's
        self._probe_options = {**defaults, **fs_options}
        self._probe_fs = None
        self._put_options = {"chunksize": max(int(part_bytes), 5 * 2**20)} if self._s3 else {}
        if not self.root:
            raise StoreError("an object-store URL names a bucket: s3://bucket/prefix")
        if check and self._s3:
            # info, not exists: exists says False for an endpoint that is down too
            self._call("reaching", self.root.split("/")[0], self.fs.info,
                       self.root.split("/")[0])

    def _path(self, key: str) -> str:
        return f"{self.root}/{check_key(key)}"

    def _call(self, doing: str, key: str, function, *args, **kwargs):
        """``function(*args)``, its failures as one-sentence store errors."""
        try:
            return function(*args, **kwargs)
        except FileNotFoundError:
            if doing == "reaching":
                raise StoreError(f"the object store has no bucket {key!r}; create it "
                                 "first") from None
            if doing == "storing":
                raise StoreError(f"the object store failed while storing {key!r}: its bucket "
                                 "does not exist") from None
            raise BlobNotFoundError(key) from None
        except PermissionError:
            raise StoreError(f"the object store refused access while {doing} {key!r}; check "
                             "the AWS credentials") from None
        except OSError as exc:
            if is_disk_full(exc):
                raise StorageFullError(f"the server ran out of disk space while {doing} "
                                       f"{key!r}; try again once space is freed") from exc
            if isinstance(exc, (ConnectionError, TimeoutError)) or _from_transport(exc):
                raise _unavailable(doing, key, exc) from exc
            raise StoreError(f"the object store failed while {doing} {key!r}: "
                             f"{_reason(exc)}") from exc
        except Exception as exc:
            # botocore's connection and timeout errors are not OSErrors
            if _from_transport(exc):
                raise _unavailable(doing, key, exc) from exc
            raise

    def put_file(self, key: str, path, *, move: bool = False) -> None:
        size = os.stat(path).st_size
        if self._s3 and size >= 2 * self._put_options["chunksize"]:
            # in parts, each under its own deadline, aborted if it does not complete
            # (s3fs's put_file leaves a cancelled upload's parts in the bucket)
            from .s3_upload import put_multipart

            bucket, _, name = self._path(key).partition("/")
            self._call("storing", key, put_multipart, self.fs, bucket, name, path,
                       part_bytes=self._put_options["chunksize"],
                       bytes_per_second=MIN_BYTES_PER_SECOND, answer_seconds=CALL_SECONDS)
            self.fs.invalidate_cache(self._path(key))
        else:
            self._call("storing", key, self.fs.put_file, os.fspath(path), self._path(key),
                       **self._put_options, **self._deadline(size))
        if move:
            Path(path).unlink(missing_ok=True)

    def put_bytes(self, key: str, data) -> None:
        data = bytes(data)
        self._call("storing", key, self.fs.pipe_file, self._path(key), data,
                   **self._deadline(len(data)))

    def _deadline(self, nbytes: int) -> dict:
        """The keyword that bounds a write of ``nbytes`` (fsspec's ``timeout=`` of an
        asynchronous file system such as s3fs, which cancels the call; none for
        others, whose writes are local)."""
        if not getattr(self.fs, "async_impl", False):
            return {}
        return {"timeout": CALL_SECONDS + nbytes / MIN_BYTES_PER_SECOND}

    def open(self, key: str) -> BinaryIO:
        # s3fs reads in ranged GETs pinned to the object's ETag: should the object
        # be replaced while it is read, a read raises OSError (FileExpired) rather
        # than mix two versions. Content-addressed keys are never replaced.
        return self._call("reading", key, self.fs.open, self._path(key), "rb")

    def get_bytes(self, key: str) -> bytes:
        # one GET: always one whole version of the object
        return self._call("reading", key, self.fs.cat_file, self._path(key))

    def get_file(self, key: str, dest) -> None:
        dest = Path(dest)
        temporary = temporary_beside(dest)
        try:
            self._call("copying", key, self.fs.get_file, self._path(key), os.fspath(temporary))
            with _local_errors(key, "copying"):
                os.replace(temporary, dest)
        finally:
            temporary.unlink(missing_ok=True)

    def exists(self, key: str) -> bool:
        return bool(self._call("reading", key, self.fs.exists, self._path(key)))

    def size(self, key: str) -> int:
        return int(self._call("reading", key, self.fs.info, self._path(key))["size"])

    def delete(self, key: str) -> None:
        try:
            self._call("deleting", key, self.fs.rm_file, self._path(key))
        except BlobNotFoundError:
            pass

    def ping(self, *, timeout: float) -> None:
        """S3: a HEAD of the bucket, through a file system of its own whose
        connection and read time out after ``timeout`` and which never retries, so
        a store that is down is said so within about ``timeout``. Other fsspec
        stores (``memory://``) are not probed."""
        if not self._s3:
            return
        if self._probe_fs is None:
            import fsspec

            protocol = self.url.split("://", 1)[0]
            config = {**self._probe_options.get("config_kwargs", {}),
                      "connect_timeout": timeout, "read_timeout": timeout,
                      "retries": {"total_max_attempts": 1}}
            probe_fs = fsspec.filesystem(protocol, **{**self._probe_options,
                                                      "config_kwargs": config,
                                                      "skip_instance_cache": True})
            probe_fs.retries = 1        # s3fs's own retry loop, over botocore's
            self._probe_fs = probe_fs
        bucket = self.root.split("/")[0]
        self._call("reaching", bucket, self._probe_fs.info, bucket)

    def keys(self, prefix: str = "") -> Iterator[str]:
        base = self._path(prefix) if prefix else self.root
        try:
            found = self._call("listing", prefix or "/", self.fs.find, base)
        except BlobNotFoundError:
            return
        # file systems differ in a leading "/" (memory://) and the protocol
        start = len(self.root) + 1
        for path in found:
            path = path.split("://", 1)[-1].strip("/")
            if path.startswith(self.root + "/"):
                yield path[start:]


def _from_transport(exc: BaseException) -> bool:
    """Whether ``exc`` comes from the HTTP layer under s3fs (a connection refused,
    reset or timed out, an endpoint that does not answer) rather than from S3."""
    return type(exc).__module__.split(".")[0] in ("botocore", "aiobotocore", "aiohttp",
                                                  "urllib3")


def _unavailable(doing: str, key: str, exc: BaseException) -> StoreUnavailable:
    # the exception's text names the endpoint: only its type is kept
    return StoreUnavailable(f"the object store could not be reached while {doing} {key!r} "
                            f"({type(exc).__name__}); try again shortly")


def _reason(exc: OSError) -> str:
    """A short reason for ``exc`` without the URL s3fs puts in some messages."""
    text = exc.strerror or str(exc) or type(exc).__name__
    return re.sub(r"\S+://\S+", "the object", text)[:200]
