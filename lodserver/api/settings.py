"""Server settings, from ``LODSERVER_*`` environment variables (pydantic-settings).

``get_settings`` is cached and used through ``Depends``, so tests override it
(``app.dependency_overrides[get_settings]``) or pass settings to ``create_app``.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Annotated

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from ..jobs import DEFAULT_MAX_TRIANGLES
from ..store import LOADED_CACHE_SIZE


class Settings(BaseSettings):
    """Everything an operator can set; defaults suit one machine and no setup."""

    model_config = SettingsConfigDict(env_prefix="LODSERVER_", extra="ignore")

    data_dir: Path = Field(Path("lodserver-data"),
                           description="Directory of the catalogue, sources and artefacts.")
    token: SecretStr | None = Field(None, description="Bearer token required by write "
                                    "endpoints; unset or empty: no token needed.")
    max_upload_bytes: int = Field(256 * 2**20, gt=0, description="Largest request body "
                                  "accepted by POST /meshes, in bytes.")
    max_triangles: int = Field(DEFAULT_MAX_TRIANGLES, gt=0,
                               description="Most triangles a mesh may have after cleaning.")
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Origins allowed by CORS: comma-separated or a JSON "
        "list; '*' for any.")
    workers: int = Field(1, ge=1, le=64, description="Concurrent builds.")
    loaded_meshes: int = Field(LOADED_CACHE_SIZE, ge=1, le=4096, description="Progressive "
                               "meshes kept in memory (least recently used dropped); each "
                               "holds its arrays and packet records: 183 MB for a mesh of "
                               "1.1M faces.")
    warm_kernels: bool = Field(True, description="Load the numba kernels at start-up, "
                               "before the first build needs them.")
    static_dir: Path = Field(Path(__file__).resolve().parents[2] / "static",
                             description="The browser viewer's files (default: the checkout's "
                             "static/ folder).")

    @field_validator("token", mode="before")
    @classmethod
    def _empty_token_is_none(cls, value):
        return None if value in ("", None) else value

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _split_origins(cls, value):
        if isinstance(value, str):
            value = value.strip()
            if value.startswith("["):
                return json.loads(value)
            return [origin.strip() for origin in value.split(",") if origin.strip()]
        return value


@lru_cache
def get_settings() -> Settings:
    return Settings()
