"""Environments CRUD and import/export of their maps."""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from app.deps import RowId, SessionDep
from app.routers.json_bodies import JsonBodyRoute
from app.schemas import EnvironmentCreate, EnvironmentOut, EnvironmentUpdate, MapDocument, Problem
from app.services import environments

router = APIRouter(prefix="/environments", tags=["environments"], route_class=JsonBodyRoute)
_404 = {404: {"model": Problem, "description": "No such environment"}}


@router.post("", status_code=status.HTTP_201_CREATED, response_model=EnvironmentOut)
def create_environment(spec: EnvironmentCreate, session: SessionDep, response: Response) -> EnvironmentOut:
    created = environments.create(session, spec)
    response.headers["Location"] = f"/environments/{created.id}"
    return created


@router.get("", response_model=list[EnvironmentOut])
def list_environments(session: SessionDep) -> list[EnvironmentOut]:
    return environments.list_all(session)


@router.get("/{environment_id}", response_model=EnvironmentOut, responses=_404)
def get_environment(environment_id: RowId, session: SessionDep) -> EnvironmentOut:
    return environments.get(session, environment_id)


@router.patch("/{environment_id}", response_model=EnvironmentOut, responses=_404)
def update_environment(
    environment_id: RowId, changes: EnvironmentUpdate, session: SessionDep
) -> EnvironmentOut:
    return environments.update(session, environment_id, changes)


@router.delete("/{environment_id}", status_code=status.HTTP_204_NO_CONTENT, responses=_404)
def delete_environment(environment_id: RowId, session: SessionDep) -> None:
    environments.delete(session, environment_id)


@router.get("/{environment_id}/map", response_model=MapDocument, responses=_404)
def get_map(environment_id: RowId, session: SessionDep) -> MapDocument:
    """The environment's map: camera and 3D disc centres of every target."""
    return environments.get_map(session, environment_id)


@router.put("/{environment_id}/map", response_model=MapDocument, responses=_404)
def put_map(environment_id: RowId, document: MapDocument, session: SessionDep) -> MapDocument:
    """Replace the map whole (a map measured by hand, or an exported one). A document
    with wrong shapes or non-finite numbers is refused whole and the stored map stays."""
    return environments.put_map(session, environment_id, document)
