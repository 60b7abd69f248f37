"""Server settings, from ``LODSERVER_*`` environment variables (pydantic-settings).

``get_settings`` is cached and used through ``Depends``, so tests override it
(``app.dependency_overrides[get_settings]``) or pass settings to ``create_app``.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Annotated

from pydantic import Field, SecretStr, ValidationInfo, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from ..io.fileset import FileSetLimits
from ..io.limits import DEFAULT_MAX_TRIANGLES
from ..service.cache import DEFAULT_CACHE_BYTES
from ..service.catalog import redact_url
from ..service.jobs import LEASE_SECONDS, POLL_SECONDS
from ..service.parsing import PARSE_MEMORY_BYTES
from ..service.store import LOADED_BYTES_PER_TRIANGLE, LOADED_CACHE_SIZE


class Settings(BaseSettings):
    """Everything an operator can set; defaults suit one machine and no setup."""

    model_config = SettingsConfigDict(env_prefix="LODSERVER_", extra="ignore")

    data_dir: Path = Field(Path("lodserver-data"),
                           description="Directory of the catalogue, sources and artefacts.")
    # token_file before token: token's validator reads it (fields validate in order)
    token_file: Path | None = Field(None, description="A file holding the bearer token (a "
                                    "Docker or Kubernetes secret), its trailing newline "
                                    "ignored; instead of token, never with it.")
    token: SecretStr | None = Field(None, validate_default=True, description="Bearer token "
                                    "required by write endpoints; unset or empty: no token "
                                    "needed.")
    header_seconds: float = Field(10.0, gt=0, le=600, description="A request whose line and "
                                  "headers have not all arrived this many seconds after its "
                                  "connection opened (or its first byte) is answered 408 and "
                                  "its connection closed (lodserver serve).")
    max_upload_bytes: int = Field(256 * 2**20, gt=0, description="Largest request body "
                                  "accepted by POST /meshes, in bytes.")
    upload_idle_seconds: float = Field(30.0, gt=0, le=3600, description="An upload whose "
                                       "body sends nothing for this long is cut (408) and "
                                       "what it sent removed.")
    upload_min_rate: int = Field(1024, ge=0, description="Bytes per second an upload's body "
                                 "must average over each upload_rate_seconds of waiting for "
                                 "it; a slower one is cut (408). 0: no minimum.")
    upload_rate_seconds: float = Field(30.0, gt=0, le=3600, description="The period over "
                                       "which upload_min_rate is measured (the first one is "
                                       "the grace period of a new upload).")
    concurrent_uploads: int = Field(16, ge=1, le=4096, description="Upload bodies received "
                                    "at once; past that, POST /meshes answers 503 with "
                                    "Retry-After before reading the body.")
    zip_unpacked_ratio: float = Field(4.0, gt=0, le=1024, description="A zip upload may "
                                      "unpack to at most this many times max_upload_bytes "
                                      "(what its files declare, checked before any is "
                                      "written).")
    queued_source_bytes: int = Field(4 * 2**30, gt=0, description="Bytes of uploads kept "
                                     "while their builds are queued or running (the stored "
                                     "files: a zip compressed); an upload that would pass it "
                                     "is answered 503 with Retry-After.")
    max_triangles: int = Field(DEFAULT_MAX_TRIANGLES, gt=0,
                               description="Most triangles a mesh may have after cleaning.")
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Origins allowed by CORS: comma-separated or a JSON "
        "list; '*' for any.")
    workers: int = Field(1, ge=0, le=64, description="Concurrent builds; 0: this server "
                         "builds nothing and leaves its uploads to other servers or "
                         "`lodserver worker` processes sharing the catalogue.")
    catalog_url: str | None = Field(None, description="The catalogue and build queue: "
                                    "postgresql://user:password@host:port/database to share "
                                    "one between servers and workers, or sqlite:///path; "
                                    "unset: catalogue.sqlite3 in data_dir.")
    store_url: str | None = Field(None, description="Where uploads and artefacts are kept: "
                                  "s3://bucket/prefix (endpoint and credentials from the AWS_* "
                                  "variables) or a folder every server sees; unset: data_dir.")
    cache_bytes: int = Field(DEFAULT_CACHE_BYTES, ge=0, description="With store_url: bytes of "
                             "artefacts read from the store kept under data_dir/cache (least "
                             "recently used removed).")
    lease_seconds: float = Field(LEASE_SECONDS, ge=2, le=600, description="A build's lease: "
                                 "a build whose server or worker died is taken over by another "
                                 "after at most this long (renewed every third of it).")
    queue_poll_seconds: float = Field(POLL_SECONDS, gt=0, le=60, description="How often an "
                                      "idle server or worker looks for builds queued by others.")
    parse_workers: int = Field(1, ge=1, le=64, description="Uploads parsed at once, each in "
                               "a worker process of its own.")
    parse_queue: int = Field(4, ge=0, le=1024, description="Uploads waiting for a parse "
                             "worker; past that, POST /meshes answers 503 with Retry-After.")
    parse_memory_bytes: int = Field(PARSE_MEMORY_BYTES, ge=2**30, description="Address space "
                                    "of each parse worker, in bytes (its imports take about "
                                    "0.5 GB); a file needing more is refused with 413.")
    loaded_meshes: int = Field(LOADED_CACHE_SIZE, ge=1, le=4096, description="Most "
                               "progressive meshes and scenes kept in memory (least recently "
                               "used dropped); loaded_bytes bounds their bytes too.")
    loaded_bytes: int | None = Field(None, ge=2**20, description="Most bytes of loaded "
                                     "meshes and scenes kept in memory (their arrays, carried "
                                     "data and packet records; least recently used dropped, "
                                     "the one in use kept); unset: what a mesh at "
                                     "max_triangles takes, at least 64 MiB.")
    warm_kernels: bool = Field(True, description="Load the numba kernels at start-up, "
                               "before the first build needs them.")
    static_dir: Path = Field(default_factory=lambda: next(
        (path for path in (Path(__file__).resolve().parents[2] / "static",   # a checkout's
                           Path(__file__).resolve().parents[1] / "_static")  # a wheel's (setup.py)
         if path.is_dir()), Path(__file__).resolve().parents[2] / "static"),
        description="The browser viewer's files (default: the checkout's static/ folder, "
        "else the copy installed with the package).")
    heavy_requests: int = Field(2, ge=1, le=64, description="Slots for encoding responses "
                                "that are in no cache (levels, scene levels, chains, packets "
                                "of unprepared records or other bits); a body takes one slot "
                                "per heavy_slot_bytes of its estimated size begun, at most "
                                "all; one of at most 1/32 of a slot takes none.")
    heavy_slot_bytes: int = Field(64 * 2**20, ge=1024, description="Estimated body bytes "
                                  "one heavy slot stands for: bodies of at most "
                                  "heavy_requests x this many bytes are encoded at once, or "
                                  "one larger body alone.")
    heavy_wait_seconds: float = Field(1.0, ge=0, le=60, description="How long a request "
                                      "waits for a slot before a 503 with Retry-After.")
    body_file_bytes: int = Field(8 * 2**20, ge=0, description="Bodies larger than this "
                                 "are written once to a file under data_dir/bodies and "
                                 "streamed from it; smaller ones are cached in memory.")
    body_cache_bytes: int = Field(2 * 2**30, ge=0, description="Most bytes of body files "
                                  "kept (least recently used removed).")

    @property
    def set_limits(self) -> FileSetLimits:
        """What an upload of several files or a zip may hold, its unpacked size tied
        to the largest upload."""
        return FileSetLimits(max_unpacked_bytes=int(self.zip_unpacked_ratio
                                                    * self.max_upload_bytes))

    @field_validator("token", mode="before")
    @classmethod
    def _token_or_its_file(cls, value, info: ValidationInfo):
        value = None if value in ("", None) else value
        path = info.data.get("token_file")
        if path is None:
            return value
        if value is not None:
            raise ValueError("set LODSERVER_TOKEN or LODSERVER_TOKEN_FILE, not both")
        return read_token_file(path)

    @model_validator(mode="after")
    def _loaded_bytes_by_triangles(self):
        if self.loaded_bytes is None:       # room for a mesh at the limit, or many small
            self.loaded_bytes = max(LOADED_BYTES_PER_TRIANGLE * self.max_triangles, 2**26)
        return self

    @field_validator("token_file", "catalog_url", "store_url", mode="before")
    @classmethod
    def _empty_is_none(cls, value):
        return None if value in ("", None) else value

    @field_validator("catalog_url")
    @classmethod
    def _known_catalog(cls, value):
        if value is not None and value.split(":", 1)[0].lower() not in (
                "postgresql", "postgres", "sqlite"):
            raise ValueError("a catalogue URL starts with postgresql:// or sqlite://, not "
                             f"{redact_url(value)!r}")
        return value

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _split_origins(cls, value):
        if isinstance(value, str):
            value = value.strip()
            if value.startswith("["):
                return json.loads(value)
            return [origin.strip() for origin in value.split(",") if origin.strip()]
        return value


def read_token_file(path: Path) -> str:
    """The token in the file at ``path``: its text without the trailing newline
    that ``echo`` and most editors add. An unreadable or empty file is a
    ValueError (an empty token would leave the writes open)."""
    try:
        token = Path(path).read_text(encoding="utf-8").rstrip("\r\n")
    except OSError as exc:
        raise ValueError(f"cannot read the token file {str(path)!r} "
                         f"({exc.strerror or type(exc).__name__})") from None
    except UnicodeDecodeError:
        raise ValueError(f"the token file {str(path)!r} is not UTF-8 text") from None
    if not token:
        raise ValueError(f"the token file {str(path)!r} is empty")
    return token


@lru_cache
def get_settings() -> Settings:
    return Settings()
