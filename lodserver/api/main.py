"""The FastAPI app: middleware, routers, error handlers, and the lifespan that
opens the store and starts the job runner (not at import, so tests and the CLI
stay light).

Run it with ``lodserver serve`` or ``uvicorn --factory lodserver.api.main:create_app``.
"""

from __future__ import annotations

from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.concurrency import run_in_threadpool
from fastapi.middleware.cors import CORSMiddleware
from fastapi.routing import APIRoute

from ..packets import shutdown_background
from ..service.jobs import JobRunner
from ..service.parsing import ParsePool
from ..service.store import LocalStore
from .caching import BodyCache
from .errors import add_error_handlers
from .routes import health, lods, materials, meshes, parts, progressive, viewer
from .settings import Settings, get_settings


@asynccontextmanager
async def lifespan(app: FastAPI):
    settings: Settings = app.state.settings
    store = open_store(settings)
    # its worker processes start on the first parse, not here
    parser = ParsePool(workers=settings.parse_workers, queue=settings.parse_queue,
                       memory_bytes=settings.parse_memory_bytes)
    jobs = build_runner(store, settings, parser)
    jobs.start(warm=settings.warm_kernels)
    app.state.store, app.state.jobs, app.state.cache = store, jobs, BodyCache()
    app.state.readiness = health.Readiness({"catalogue": store.catalog.ping,
                                            "store": store.blobs.ping})
    try:
        yield
    finally:
        await run_in_threadpool(jobs.shutdown)
        # packet records still queued for background encoding are dropped (a
        # later request schedules them again); the one being encoded finishes
        await run_in_threadpool(shutdown_background)
        store.close()


def open_store(settings: Settings) -> LocalStore:
    """The store the settings name: the data directory, with the catalogue and
    blobs of ``LODSERVER_CATALOG_URL`` and ``LODSERVER_STORE_URL`` when set."""
    return LocalStore(settings.data_dir, loaded_meshes=settings.loaded_meshes,
                      loaded_bytes=settings.loaded_bytes,
                      catalog=settings.catalog_url, blobs=settings.store_url,
                      cache_bytes=settings.cache_bytes)


def build_runner(store: LocalStore, settings: Settings, parser: ParsePool) -> JobRunner:
    """The job runner of a server (or of ``lodserver worker``) by the settings."""
    return JobRunner(store, workers=settings.workers, max_triangles=settings.max_triangles,
                     parser=parser, lease_seconds=settings.lease_seconds,
                     poll_seconds=settings.queue_poll_seconds, set_limits=settings.set_limits)


def _operation_id(route: APIRoute) -> str:
    """Stable OpenAPI operation ids (``meshes-create_mesh``) for generated clients."""
    return f"{route.tags[0]}-{route.name}" if route.tags else route.name


def create_app(settings: Settings | None = None) -> FastAPI:
    """The app, configured by ``settings`` (default: ``get_settings()``, the environment).

    Explicit settings also override the ``get_settings`` dependency, so every
    part of the app sees the same ones.
    """
    settings = settings or get_settings()
    app = FastAPI(title="lodserver", summary="Progressive-mesh level-of-detail service",
                  lifespan=lifespan, generate_unique_id_function=_operation_id)
    app.state.settings = settings
    app.dependency_overrides[get_settings] = lambda: settings
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "POST", "DELETE"],
                           allow_headers=["Authorization", "If-None-Match", "Range"],
                           expose_headers=["ETag", "Location", "Content-Range",
                                           "Accept-Ranges"])
    add_error_handlers(app)
    for module in (meshes, lods, parts, progressive, materials, health, viewer):
        app.include_router(module.router)
    viewer.mount_static(app, settings)
    from .bodies import add_bounded_reads   # body files, heavy-request limit, security headers
    add_bounded_reads(app, settings)
    return app
