"""Environments and their maps: each public function is one transaction."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.markers import get_family
from app.db import utcnow
from app.models import Environment, MapVersion, SurveyMap
from app.schemas import (EnvironmentCreate, EnvironmentOut, EnvironmentUpdate, MapChange, MapDocument,
                         MapVersionOut)
from app.services import classifiers
from app.services.errors import Conflict, Invalid, NoMap, NotFound, can_match, get_or_404

#: Earlier maps kept per environment (`MapVersion`), the newest first.
MAP_VERSIONS_KEPT = 20


def to_out(environment: Environment, has_map: bool) -> EnvironmentOut:
    return EnvironmentOut(
        id=environment.id,
        name=environment.name,
        marker_size_m=environment.marker_size_m,
        marker_family=environment.marker_family,
        classifier_id=environment.classifier_id,
        has_map=has_map,
        created_at=environment.created_at,
        updated_at=environment.updated_at,
    )


def get_row(session: Session, environment_id: int) -> Environment:
    """The environment's row, or NotFound."""
    return get_or_404(session, Environment, environment_id, "environment")


def stored_map(session: Session, environment_id: int) -> SurveyMap | None:
    """The environment's stored map row, if it has one."""
    return session.scalar(select(SurveyMap).where(SurveyMap.environment_id == environment_id))


def _has_map(session: Session, environment_id: int) -> bool:
    found = session.scalar(select(SurveyMap.id).where(SurveyMap.environment_id == environment_id))
    return found is not None


def _check_classifier(session: Session, classifier_id: int | None) -> None:
    if classifier_id is None:
        return
    try:
        classifiers.get_row(session, classifier_id)
    except NotFound:
        raise Invalid(f"classifier_id: classifier {classifier_id} does not exist") from None


def create(session: Session, spec: EnvironmentCreate) -> EnvironmentOut:
    _check_classifier(session, spec.classifier_id)
    environment = Environment(**spec.model_dump())
    session.add(environment)
    session.commit()
    return to_out(environment, has_map=False)


def list_all(session: Session) -> list[EnvironmentOut]:
    environments = session.scalars(select(Environment).order_by(Environment.id)).all()
    with_map = set(session.scalars(select(SurveyMap.environment_id)).all())
    return [to_out(e, e.id in with_map) for e in environments]


def get(session: Session, environment_id: int) -> EnvironmentOut:
    environment = get_row(session, environment_id)
    return to_out(environment, _has_map(session, environment_id))


def update(session: Session, environment_id: int, changes: EnvironmentUpdate) -> EnvironmentOut:
    environment = get_row(session, environment_id)
    fields = changes.model_dump(exclude_unset=True)
    for required in ("name", "marker_size_m"):
        if required in fields and fields[required] is None:
            raise Invalid(f"{required}: may not be null")
    if "classifier_id" in fields:
        _check_classifier(session, fields["classifier_id"])
    for name, value in fields.items():
        setattr(environment, name, value)
    session.commit()
    return to_out(environment, _has_map(session, environment_id))


def delete(session: Session, environment_id: int) -> None:
    session.delete(get_row(session, environment_id))
    session.commit()


def get_map(session: Session, environment_id: int) -> MapDocument:
    get_row(session, environment_id)
    stored = stored_map(session, environment_id)
    if stored is None:
        raise NoMap(environment_id)
    return MapDocument.model_validate(stored.document)


def put_map(session: Session, environment_id: int, document: MapDocument,
            change: MapChange = MapChange.IMPORT) -> MapDocument:
    """Replace the environment's map whole, in one transaction; a refused document
    leaves the stored map as it was, and the map it replaces is kept as a version."""
    stage_map(session, environment_id, document, change)
    session.commit()
    return document


def stage_map(session: Session, environment_id: int, document: MapDocument, change: MapChange) -> None:
    """Check `document` against the environment and stage it as the new map, keeping the
    map it replaces as a version (`change` says what replaced it); the caller commits (a
    survey job commits it together with its own success)."""
    environment = get_row(session, environment_id)
    family = get_family(environment.marker_family)
    outside = sorted(t.id for t in document.targets if t.id >= len(family))
    if outside:
        raise Invalid(
            f"targets: ids {outside[:10]} are outside family {family.name} (0..{len(family) - 1})"
        )
    stored = stored_map(session, environment_id)
    if stored is None:
        stored = SurveyMap(environment_id=environment_id)
        session.add(stored)
    else:
        _keep_version(session, stored, change)
    stored.frame = document.frame
    stored.n_targets = len(document.targets)
    stored.rms_px = document.rms_px
    stored.survey_job_id = document.survey_job_id
    stored.document = document.model_dump(mode="json")
    # The map is part of the environment: its row's own onupdate sees only its columns.
    environment.updated_at = utcnow()


def _keep_version(session: Session, stored: SurveyMap, change: MapChange) -> None:
    """Keep the map about to be replaced; drop the versions beyond `MAP_VERSIONS_KEPT`."""
    session.add(MapVersion(environment_id=stored.environment_id, frame=stored.frame, n_targets=stored.n_targets,
                           survey_job_id=stored.survey_job_id, document=stored.document, replaced_by=change.value,
                           replaced_at=utcnow()))
    session.flush()
    old = session.scalars(select(MapVersion).where(MapVersion.environment_id == stored.environment_id)
                          .order_by(MapVersion.id.desc()).offset(MAP_VERSIONS_KEPT)).all()
    for version in old:
        session.delete(version)


def map_versions(session: Session, environment_id: int) -> list[MapVersionOut]:
    """The environment's earlier maps, the newest first."""
    get_row(session, environment_id)
    rows = session.scalars(select(MapVersion).where(MapVersion.environment_id == environment_id)
                           .order_by(MapVersion.id.desc())).all()
    return [MapVersionOut(version=row.id, frame=row.frame, n_targets=row.n_targets,  # type: ignore[arg-type]
                          survey_job_id=row.survey_job_id, replaced_by=MapChange(row.replaced_by),
                          replaced_at=row.replaced_at) for row in rows]


def restore_map(session: Session, environment_id: int, version: int | None) -> MapDocument:
    """Make an earlier map (the newest if `version` is None) the environment's map again;
    the map it replaces is kept as a version in turn, so a restore loses nothing either."""
    get_row(session, environment_id)
    query = select(MapVersion).where(MapVersion.environment_id == environment_id)
    if version is None:
        row = session.scalar(query.order_by(MapVersion.id.desc()).limit(1))
        if row is None:
            raise Conflict(f"environment {environment_id} has no earlier map to restore")
    else:
        row = session.scalar(query.where(MapVersion.id == version)) if can_match(version) else None
        if row is None:
            raise NotFound(f"environment {environment_id} has no map version {version}")
    return put_map(session, environment_id, MapDocument.model_validate(row.document), MapChange.RESTORE)
