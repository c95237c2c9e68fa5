"""Environments and their maps: each public function is one transaction."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.markers import get_family
from app.db import utcnow
from app.models import Environment, SurveyMap
from app.schemas import EnvironmentCreate, EnvironmentOut, EnvironmentUpdate, MapDocument
from app.services import classifiers
from app.services.errors import Invalid, NoMap, NotFound, get_or_404


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


def put_map(session: Session, environment_id: int, document: MapDocument) -> MapDocument:
    """Replace the environment's map whole, in one transaction; a refused document
    leaves the stored map as it was."""
    stage_map(session, environment_id, document)
    session.commit()
    return document


def stage_map(session: Session, environment_id: int, document: MapDocument) -> None:
    """Check `document` against the environment and stage it as the new map; the caller
    commits (a survey job commits it together with its own success)."""
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
    stored.frame = document.frame
    stored.n_targets = len(document.targets)
    stored.rms_px = document.rms_px
    stored.survey_job_id = document.survey_job_id
    stored.document = document.model_dump(mode="json")
    # The map is part of the environment: its row's own onupdate sees only its columns.
    environment.updated_at = utcnow()
