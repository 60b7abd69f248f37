"""The catalogue: upload, list, inspect and delete meshes."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import ValidationError

from ...mesh import MeshError
from ..deps import JobsDep, MeshId, StoreDep, TokenDep, UploadDep
from ..models import MeshCreate, MeshCreated, MeshList, MeshPublic, Message

router = APIRouter(prefix="/meshes", tags=["meshes"])

_UPLOAD_BODY = {
    "required": True,
    "content": {"multipart/form-data": {"schema": {
        "type": "object", "required": ["file"],
        "properties": {
            "file": {"type": "string", "format": "binary",
                     "description": "OBJ, PLY, STL, OFF, glTF (self-contained) or GLB file."},
            **{name: {k: v for k, v in field.items() if k != "title"}
               for name, field in MeshCreate.model_json_schema()["properties"].items()},
        }}}},
}
_ERRORS = {code: {"model": Message} for code in (401, 404, 409, 413, 415, 422, 503, 507)}


@router.post("", status_code=202, response_model=MeshCreated,
             openapi_extra={"requestBody": _UPLOAD_BODY},
             responses={code: _ERRORS[code] for code in (401, 413, 415, 422, 503, 507)})
async def create_mesh(upload: UploadDep, jobs: JobsDep, response: Response) -> MeshCreated:
    """Upload a mesh; its progressive mesh is built in the background (poll the href).

    The file is parsed and checked before the answer (a parse worker process,
    a few at a time): 503 with Retry-After when that queue is full, 507 when
    the server has no disk space for it.
    """
    try:
        form = MeshCreate.model_validate(upload.fields)
    except ValidationError as exc:
        raise MeshError("; ".join(f"form field {'.'.join(map(str, e['loc']))!r}: {e['msg']}"
                                  for e in exc.errors())) from None
    # a thread waits for the parse worker (and the store's rename and row)
    record = await run_in_threadpool(jobs.accept, source=upload.path, root=upload.folder,
                                     name=form.name or upload.filename,
                                     file_type=upload.file_type, options=form.build_options())
    href = f"/meshes/{record.id}"
    response.headers["Location"] = href
    return MeshCreated(id=record.id, status=record.status, href=href)


@router.get("", response_model=MeshList)
def list_meshes(store: StoreDep, limit: Annotated[int, Query(ge=1, le=1000)] = 100,
                offset: Annotated[int, Query(ge=0, le=2**31)] = 0) -> MeshList:
    """Meshes, newest first."""
    return MeshList(meshes=[MeshPublic.from_record(r)
                            for r in store.list(limit=limit, offset=offset)])


@router.get("/{mesh_id}", response_model=MeshPublic, responses={404: _ERRORS[404]})
def get_mesh(mesh_id: MeshId, store: StoreDep) -> MeshPublic:
    """Status, build progress, counts and error curve of one mesh."""
    return MeshPublic.from_record(store.get(mesh_id=mesh_id))


@router.delete("/{mesh_id}", status_code=204, response_class=Response,
               responses={code: _ERRORS[code] for code in (401, 404)})
def delete_mesh(mesh_id: MeshId, jobs: JobsDep, _: TokenDep) -> Response:
    """Delete a mesh and its files, stopping its build if it has not finished."""
    jobs.forget(mesh_id=mesh_id)
    return Response(status_code=204)
