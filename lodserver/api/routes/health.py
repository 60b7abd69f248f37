"""Liveness for load balancers and the container HEALTHCHECK."""

from __future__ import annotations

from fastapi import APIRouter

from ..deps import StoreDep

router = APIRouter(tags=["health"])


@router.get("/healthz")
def healthz(store: StoreDep) -> dict:
    """``{"status": "ok"}`` while the catalogue answers."""
    store.list(limit=1)
    return {"status": "ok"}
