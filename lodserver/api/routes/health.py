"""Liveness and readiness for load balancers, orchestrators and the container HEALTHCHECK."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from ..deps import JobsDep

router = APIRouter(tags=["health"])


@router.get("/healthz", responses={503: {"description": "Up, but the kernels are still "
                                         "warming: do not route builds here yet."}})
async def healthz(jobs: JobsDep) -> JSONResponse:
    """``{"status": "ok", "ready": true}`` once the numba kernels are warm
    (``LODSERVER_WARM_KERNELS``), else 503 with ``"ready": false``.

    It reads one flag on the event loop, no store or disk, so it answers at
    once however busy the server is (a worker thread could be all taken).
    """
    ready = jobs.ready.is_set()
    return JSONResponse({"status": "ok", "ready": ready}, status_code=200 if ready else 503)
