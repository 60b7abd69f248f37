"""The catalogue: upload, list, inspect and delete meshes."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import ValidationError

from ...io.limits import LimitError
from ...mesh import MeshError
from ...service.store import Status
from ..deps import JobsDep, MeshId, SettingsDep, StoreDep, TokenDep, UploadDep
from ..models import MeshCreate, MeshCreated, MeshList, MeshPublic, Message, report_warnings
from ..upload import UploadsBusy, prepare_source

router = APIRouter(prefix="/meshes", tags=["meshes"])

_UPLOAD_BODY = {
    "required": True,
    "content": {"multipart/form-data": {"schema": {
        "type": "object", "required": ["file"],
        "properties": {
            "file": {"type": "array", "items": {"type": "string", "format": "binary"},
                     "description": "One mesh file (OBJ, PLY, STL, OFF, glTF or GLB); or "
                     "a mesh file and the files it names (an OBJ's .mtl and textures, a "
                     ".gltf's .bin and images), one part each; or one .zip of them. "
                     "References resolve only inside the upload."},
            "main": {"type": "string", "description": "Which file of a set is the mesh to "
                     "build, when it holds more than one mesh file."},
            **{name: {k: v for k, v in field.items() if k != "title"}
               for name, field in MeshCreate.model_json_schema()["properties"].items()},
        }}}},
}
_ERRORS = {code: {"model": Message} for code in (401, 404, 408, 409, 413, 415, 422, 503,
                                                   507)}
# Seconds a client refused for a full build queue is told to wait: builds take that long.
QUEUE_RETRY_AFTER = 30


def _check_room(store, *, size: int, budget: int) -> None:
    """Refuse a source of ``size`` bytes that would take the sources the build queue
    holds past ``budget`` bytes: 503 while builds may free room, 413 if it never fits.
    Checked before the parse, so concurrent uploads may pass it together by at most
    what the parse queue admits."""
    if size > budget:
        raise LimitError(f"the upload keeps {size} bytes while it is built; this server "
                         f"keeps at most {budget} for all queued builds")
    held = store.held_source_bytes()
    if held + size > budget:
        raise UploadsBusy(f"the server holds {held} bytes of uploads waiting to be built; "
                          f"try again in {QUEUE_RETRY_AFTER} seconds",
                          retry_after=QUEUE_RETRY_AFTER)


@router.post("", status_code=202, response_model=MeshCreated,
             openapi_extra={"requestBody": _UPLOAD_BODY},
             responses={code: _ERRORS[code] for code in (401, 408, 413, 415, 422, 503, 507)})
async def create_mesh(upload: UploadDep, jobs: JobsDep, settings: SettingsDep,
                      response: Response) -> MeshCreated:
    """Upload a mesh (or a set of files, or a zip); its progressive mesh is built in
    the background (poll the href).

    The file is parsed and checked before the answer (a parse worker process,
    a few at a time): 503 with Retry-After when that queue is full, when as
    many bodies are arriving as the server takes at once, or when the uploads
    waiting for their builds hold the server's budget of bytes; 408 for a body
    that stalls or trickles; 507 when the server has no disk space for it.
    ``warnings`` says what the load left out (a material library named but not
    uploaded, data not kept).
    """
    fields = dict(upload.fields)
    main = fields.pop("main", None)
    try:
        form = MeshCreate.model_validate(fields)
    except ValidationError as exc:
        raise MeshError("; ".join(f"form field {'.'.join(map(str, e['loc']))!r}: "
                                  f"{e['msg'].removeprefix('Value error, ')}"
                                  for e in exc.errors())) from None
    # threads: a set is copied into one archive (a zip only listed: it is unpacked
    # once, by its parse), the catalogue asked, and the parse worker waited for
    # (with the store's rename and row)
    source = await run_in_threadpool(prepare_source, upload, main=main,
                                     limits=settings.set_limits)
    size = source.path.stat().st_size
    await run_in_threadpool(_check_room, jobs.store, size=size,
                            budget=settings.queued_source_bytes)
    record, report = await run_in_threadpool(
        jobs.accept, source=source.path, root=source.root, name=form.name or source.name,
        file_type=source.file_type, options=form.build_options(), with_report=True)
    href = f"/meshes/{record.id}"
    response.headers["Location"] = href
    return MeshCreated(id=record.id, status=record.status, href=href, main=source.name,
                       files=list(source.files), warnings=report_warnings(report.as_dict()))


def _public(store, record, *, parts: bool = True) -> MeshPublic:
    """The record as clients see it, with its place in the build queue."""
    public = MeshPublic.from_record(record, parts=parts)
    if record.status is Status.QUEUED:
        public.queue_position = store.queue_position(mesh_id=record.id)
    return public


@router.get("", response_model=MeshList)
def list_meshes(store: StoreDep, limit: Annotated[int, Query(ge=1, le=1000)] = 100,
                offset: Annotated[int, Query(ge=0, le=2**31)] = 0) -> MeshList:
    """Meshes, newest first; each mesh's parts are in ``GET /meshes/{id}``."""
    return MeshList(meshes=[_public(store, r, parts=False)
                            for r in store.list(limit=limit, offset=offset)])


@router.get("/{mesh_id}", response_model=MeshPublic, responses={404: _ERRORS[404]})
def get_mesh(mesh_id: MeshId, store: StoreDep) -> MeshPublic:
    """Status, build progress, counts and error curve of one mesh."""
    return _public(store, store.get(mesh_id=mesh_id))


@router.delete("/{mesh_id}", status_code=204, response_class=Response,
               responses={code: _ERRORS[code] for code in (401, 404)})
def delete_mesh(mesh_id: MeshId, jobs: JobsDep, _: TokenDep) -> Response:
    """Delete a mesh and its files, stopping its build if it has not finished."""
    jobs.forget(mesh_id=mesh_id)
    return Response(status_code=204)
