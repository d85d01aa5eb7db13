"""`/maps`: saved, versioned maps."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Response
from fastapi.responses import FileResponse

from service.app.api.deps import Control, Read, Runtime
from service.app.api.schemas import ID_PATTERN, SavedMap, SavedMapList, errors

router = APIRouter(prefix="/maps", tags=["maps"], dependencies=Read)

MapId = Annotated[str, Path(pattern=ID_PATTERN, max_length=64, description="saved map id")]
Version = Annotated[int, Path(ge=1, le=1_000_000, description="version, from 1")]


@router.get(
    "",
    response_model=SavedMapList,
    summary="List saved maps",
    description="Every saved map version, by map id then version.",
    responses=errors(401),
)
def list_maps(runtime: Runtime) -> SavedMapList:
    return SavedMapList(maps=[SavedMap.of(m) for m in runtime.maps.list()])


def _file(runtime: Runtime, map_id: str, version: int, name: str, media_type: str) -> FileResponse:
    return FileResponse(runtime.maps.file(map_id, version, name), media_type=media_type)


@router.get(
    "/{map_id}/{version}/map.png",
    response_class=FileResponse,
    response_model=None,
    summary="Saved map as PNG",
    description="The PNG of one saved map version (white free, black occupied, grey unknown).",
    responses={200: {"content": {"image/png": {}}, "description": "PNG"}, **errors(401, 404, 422)},
)
def saved_png(map_id: MapId, version: Version, runtime: Runtime) -> FileResponse:
    return _file(runtime, map_id, version, "map.png", "image/png")


@router.get(
    "/{map_id}/{version}/map.pgm",
    response_class=FileResponse,
    response_model=None,
    summary="Saved map as PGM (ROS map_server)",
    description="The PGM image of one saved map version, to pair with its `map.yaml`.",
    responses={
        200: {"content": {"image/x-portable-graymap": {}}, "description": "PGM"},
        **errors(401, 404, 422),
    },
)
def saved_pgm(map_id: MapId, version: Version, runtime: Runtime) -> FileResponse:
    return _file(runtime, map_id, version, "map.pgm", "image/x-portable-graymap")


@router.get(
    "/{map_id}/{version}/map.yaml",
    response_class=FileResponse,
    response_model=None,
    summary="Saved map metadata (ROS map_server YAML)",
    description="Resolution, origin and thresholds of one saved map version; image `map.pgm`.",
    responses={
        200: {"content": {"application/yaml": {}}, "description": "YAML"},
        **errors(401, 404, 422),
    },
)
def saved_yaml(map_id: MapId, version: Version, runtime: Runtime) -> FileResponse:
    return _file(runtime, map_id, version, "map.yaml", "application/yaml")


@router.delete(
    "/{map_id}/{version}",
    status_code=204,
    response_class=Response,
    response_model=None,
    dependencies=Control,
    summary="Delete a saved map version",
    description="Delete one saved version of a map (its PNG, PGM, YAML). Other versions stay.",
    responses=errors(401, 404, 422),
)
def delete_saved_map(map_id: MapId, version: Version, runtime: Runtime) -> Response:
    runtime.maps.delete(map_id, version, runtime.data.trash_dir)
    return Response(status_code=204)
