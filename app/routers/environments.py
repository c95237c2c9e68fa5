"""Environments CRUD, import/export of their maps, and their FreeD output."""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from app.deps import RowId, SessionDep, SettingsDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.preconditions import IfMatchDep, map_etag_reply, set_map_etag
from app.routers.responses import MAP_CHANGED, NO_MAP, invalid, not_found, problem
from app.schemas import (EnvironmentCreate, EnvironmentOut, EnvironmentUpdate, FreeDOutput, MapDocument,
                         MapRestoreRequest, MapVersionOut)
from app.services import environments, freed

router = APIRouter(prefix="/environments", tags=["environments"], route_class=JsonBodyRoute)
_404 = not_found("environment")
_422 = invalid()


@router.post("", status_code=status.HTTP_201_CREATED, response_model=EnvironmentOut, summary="Create an environment",
             responses=_422)
def create_environment(spec: EnvironmentCreate, session: SessionDep, response: Response) -> EnvironmentOut:
    """A new environment, without a map yet (``Location: /environments/{id}``). Its
    marker family cannot change later; its name, card size and classifier can."""
    created = environments.create(session, spec)
    response.headers["Location"] = f"/environments/{created.id}"
    return created


@router.get("", response_model=list[EnvironmentOut], summary="List the environments")
def list_environments(session: SessionDep) -> list[EnvironmentOut]:
    """Every environment, oldest first."""
    return environments.list_all(session)


@router.get("/{environment_id}", response_model=EnvironmentOut, summary="Get an environment",
            responses={**_404, **_422})
def get_environment(environment_id: RowId, session: SessionDep) -> EnvironmentOut:
    """One environment: its cards, its classifier and whether it has a map."""
    return environments.get(session, environment_id)


@router.patch("/{environment_id}", response_model=EnvironmentOut, summary="Change an environment",
              responses={**_404, **_422})
def update_environment(
    environment_id: RowId, changes: EnvironmentUpdate, session: SessionDep
) -> EnvironmentOut:
    """Rename an environment, or change its printed card size or its classifier: the
    fields given change, the others stay."""
    return environments.update(session, environment_id, changes)


@router.delete("/{environment_id}", status_code=status.HTTP_204_NO_CONTENT, summary="Delete an environment",
               responses={**_404, **_422})
def delete_environment(environment_id: RowId, session: SessionDep) -> None:
    """Delete an environment with its map and its jobs."""
    environments.delete(session, environment_id)


@router.get("/{environment_id}/map", response_model=MapDocument, summary="Export the map",
            responses={**map_etag_reply("The map"), **_404, **_422, **NO_MAP})
def get_map(environment_id: RowId, session: SessionDep, response: Response) -> MapDocument:
    """The environment's map: camera and 3D disc centres of every target. Its revision
    is the reply's ``ETag``: a change made from this map sends it back in ``If-Match``."""
    stored = environments.get_map(session, environment_id)
    set_map_etag(response, stored.revision)
    return stored.document


@router.put("/{environment_id}/map", response_model=MapDocument, summary="Import a map",
            responses={**map_etag_reply("The map stored"), **_404, **_422, **MAP_CHANGED})
def put_map(environment_id: RowId, document: MapDocument, session: SessionDep, response: Response,
            if_match: IfMatchDep) -> MapDocument:
    """Replace the map whole (a map measured by hand, or an exported one). A document
    with wrong shapes or non-finite numbers is refused whole and the stored map stays;
    the map it replaces is kept as a version (`GET .../map/versions`). With ``If-Match``
    it is stored only over the map at that revision (else 412)."""
    stored = environments.put_map(session, environment_id, document, if_match=if_match)
    set_map_etag(response, stored.revision)
    return stored.document


@router.get("/{environment_id}/map/versions", response_model=list[MapVersionOut], summary="List earlier maps",
            responses={**_404, **_422})
def list_map_versions(environment_id: RowId, session: SessionDep) -> list[MapVersionOut]:
    """The maps the environment had before each import, survey, alignment or restore
    replaced them, the newest first (the last 20)."""
    return environments.map_versions(session, environment_id)


@router.post("/{environment_id}/map/restore", response_model=MapDocument, summary="Restore an earlier map",
             responses={**map_etag_reply("The map restored"), **_404, **_422,
                        **problem(409, "No earlier map to restore"), **MAP_CHANGED})
def restore_map(environment_id: RowId, spec: MapRestoreRequest, session: SessionDep, response: Response,
                if_match: IfMatchDep) -> MapDocument:
    """Make an earlier map the environment's map again: the one the last change replaced
    (body ``{}``), or the `version` given. The map it replaces is kept as a version in
    turn, so that a restore can be undone too. With ``If-Match`` it replaces only the
    map at that revision (else 412)."""
    stored = environments.restore_map(session, environment_id, spec.version, if_match=if_match)
    set_map_etag(response, stored.revision)
    return stored.document


_404_FREED = problem(404, "No such environment, or it has no FreeD output")


@router.get("/{environment_id}/freed", response_model=FreeDOutput, summary="Get the FreeD output",
            responses={**_404_FREED, **_422})
def get_freed(environment_id: RowId, session: SessionDep) -> FreeDOutput:
    """Where the environment's /track connections send their poses as FreeD packets (404
    when it has no FreeD output)."""
    return freed.get(session, environment_id)


@router.put("/{environment_id}/freed", response_model=FreeDOutput, summary="Set the FreeD output",
            responses={**_404, **_422})
def put_freed(environment_id: RowId, output: FreeDOutput, session: SessionDep, settings: SettingsDep) -> FreeDOutput:
    """Send every pose tracked in this environment as a FreeD D1 packet over UDP to a
    receiver (Unreal Engine's LiveLink FreeD source, Aximmetry, Disguise): docs/freed.md.
    Connections opened afterwards use it; a connection can choose its own camera id or
    opt out in its config (`freed`). A loopback, link-local, multicast, broadcast,
    unspecified or reserved address is refused (422) unless the server's
    `freed_allowed_networks` lists it; a host name is checked by its addresses when a
    connection uses it."""
    return freed.put(session, environment_id, output, policy=freed.FreeDPolicy.from_settings(settings))


@router.delete("/{environment_id}/freed", status_code=status.HTTP_204_NO_CONTENT, summary="Remove the FreeD output",
               responses={**_404_FREED, **_422})
def delete_freed(environment_id: RowId, session: SessionDep) -> None:
    """Stop sending FreeD packets for the connections opened afterwards."""
    freed.delete(session, environment_id)
