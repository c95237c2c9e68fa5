"""Environments and their maps: each public function is one transaction.

Every change of a map goes through `replace_map`: under the write lock on the environment
it reads the current map, checks the writer's precondition (``If-Match``) against its
revision, makes the new map, keeps the current one as a version and stores the new one
at the next revision. Writers are so serialised: none works from a map another has
replaced meanwhile, and each map replaced is kept once."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.markers import get_family
from app.db import lock_row_for_writing, utcnow
from app.models import Environment, MapVersion, SurveyMap
from app.schemas import (EnvironmentCreate, EnvironmentOut, EnvironmentUpdate, MapChange, MapDocument,
                         MapVersionOut)
from app.services import classifiers
from app.services.errors import Conflict, Invalid, NoMap, NotFound, PreconditionFailed, can_match, get_or_404

#: Earlier maps kept per environment (`MapVersion`), the newest first.
MAP_VERSIONS_KEPT = 20


@dataclass(frozen=True)
class MapRevision:
    """An environment's map and its revision: a number that grows by one with every
    change of the map (the ``ETag`` of the map's replies)."""

    document: MapDocument
    revision: int


@dataclass(frozen=True)
class IfMatch:
    """What a conditional write requires of the map it replaces (HTTP ``If-Match``): any
    map (``*``), or the map at one of `revisions`. No map at all meets neither."""

    revisions: frozenset[int] = frozenset()
    any_map: bool = False

    def met_by(self, revision: int | None) -> bool:
        return revision is not None and (self.any_map or revision in self.revisions)

    def __str__(self) -> str:
        return "*" if self.any_map else ", ".join(f'"{r}"' for r in sorted(self.revisions)) or "no revision of it"


#: What a writer makes the new map of: the current one (None without one).
NewMap = Callable[[MapDocument | None], MapDocument]


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


def map_version(session: Session, environment_id: int) -> str | None:
    """The version of the environment's stored map (a new one on every change, whichever
    process made it), read without the document; None without a map."""
    current = session.execute(select(SurveyMap.id, SurveyMap.updated_at)
                              .where(SurveyMap.environment_id == environment_id)).one_or_none()
    return None if current is None else version_of(current.id, current.updated_at)


def version_of(map_id: int, updated_at: datetime) -> str:
    """A stored map's version from its id and its last change."""
    return f"{map_id}:{updated_at.isoformat()}"


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


def get_map(session: Session, environment_id: int) -> MapRevision:
    get_row(session, environment_id)
    stored = stored_map(session, environment_id)
    if stored is None:
        raise NoMap(environment_id)
    return MapRevision(MapDocument.model_validate(stored.document), stored.revision)


def replace_map(session: Session, environment_id: int, change: MapChange, new_map: MapDocument | NewMap, *,
                if_match: IfMatch | None = None, commit: bool = True) -> MapRevision:
    """Replace the environment's map: the one way a map changes (see the module docstring).

    Under the write lock on the environment (`lock_row_for_writing`, held until the
    transaction ends), reads the current map, refuses with PreconditionFailed when it
    does not meet `if_match`, makes the new map (`new_map`, or `new_map(current)`), checks
    it against the environment, keeps the current map as a version (`change` says what
    replaced it) and stores the new one at the next revision. What the session holds is
    committed first: the lock is taken as the transaction begins. With `commit` False
    the caller commits (a survey job commits the map with its own success)."""
    session.commit()
    try:
        environment = lock_row_for_writing(session, Environment, environment_id) if can_match(environment_id) else None
        if environment is None:
            raise NotFound(f"environment {environment_id} not found")
        stored = session.scalar(select(SurveyMap).where(SurveyMap.environment_id == environment_id)
                                .execution_options(populate_existing=True))
        if if_match is not None and not if_match.met_by(stored.revision if stored is not None else None):
            raise _precondition_failed(environment_id, stored, if_match)
        if isinstance(new_map, MapDocument):
            document = new_map
        else:
            document = new_map(MapDocument.model_validate(stored.document) if stored is not None else None)
        _check_family(environment, document)
        if stored is None:
            stored = SurveyMap(environment_id=environment_id, revision=1)
            session.add(stored)
        else:
            _keep_version(session, stored, change)
            stored.revision += 1
        stored.frame = document.frame
        stored.n_targets = len(document.targets)
        stored.rms_px = document.rms_px
        stored.survey_job_id = document.survey_job_id
        stored.document = document.model_dump(mode="json")
        # The map is part of the environment: its row's own onupdate sees only its columns.
        environment.updated_at = utcnow()
        revision = stored.revision
        if commit:
            session.commit()
    except BaseException:
        if commit:
            session.rollback()  # the write lock goes now, not when the session closes
        raise
    return MapRevision(document, revision)


def _precondition_failed(environment_id: int, stored: SurveyMap | None, if_match: IfMatch) -> PreconditionFailed:
    if stored is None:
        return PreconditionFailed(f"environment {environment_id} has no map, so If-Match ({if_match}) matches "
                                  "none: nothing was changed; send the map without If-Match to store the first one")
    return PreconditionFailed(
        f"the map of environment {environment_id} changed since it was read: it is at revision {stored.revision} "
        f'(ETag "{stored.revision}") and If-Match named {if_match}. Nothing was changed: read the map again (GET '
        ".../map gives its ETag), redo the change on it and send it with that ETag in If-Match")


def put_map(session: Session, environment_id: int, document: MapDocument, change: MapChange = MapChange.IMPORT,
            *, if_match: IfMatch | None = None) -> MapRevision:
    """Replace the environment's map whole with `document` (`replace_map`): a refused
    document leaves the stored map as it was, and the map it replaces is kept as a version."""
    return replace_map(session, environment_id, change, document, if_match=if_match)


def stage_map(session: Session, environment_id: int, document: MapDocument, change: MapChange) -> MapRevision:
    """`put_map` that the caller commits (a survey job commits the map together with its
    own success); the write lock is held until it does."""
    return replace_map(session, environment_id, change, document, commit=False)


def _check_family(environment: Environment, document: MapDocument) -> None:
    """Invalid when a target of `document` is outside the environment's marker family."""
    family = get_family(environment.marker_family)
    outside = sorted(t.id for t in document.targets if t.id >= len(family))
    if outside:
        raise Invalid(
            f"targets: ids {outside[:10]} are outside family {family.name} (0..{len(family) - 1})"
        )


def _keep_version(session: Session, stored: SurveyMap, change: MapChange) -> None:
    """Keep the map about to be replaced; drop the versions beyond `MAP_VERSIONS_KEPT`."""
    session.add(MapVersion(environment_id=stored.environment_id, frame=stored.frame, n_targets=stored.n_targets,
                           survey_job_id=stored.survey_job_id, document=stored.document, revision=stored.revision,
                           replaced_by=change.value, replaced_at=utcnow()))
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
                          survey_job_id=row.survey_job_id, revision=row.revision, replaced_by=MapChange(row.replaced_by),
                          replaced_at=row.replaced_at) for row in rows]


def restore_map(session: Session, environment_id: int, version: int | None, *,
                if_match: IfMatch | None = None) -> MapRevision:
    """Make an earlier map (the newest if `version` is None) the environment's map again
    (`replace_map`); the map it replaces is kept as a version in turn, so a restore loses
    nothing either."""

    def earlier(_current: MapDocument | None) -> MapDocument:
        query = select(MapVersion).where(MapVersion.environment_id == environment_id)
        if version is None:
            row = session.scalar(query.order_by(MapVersion.id.desc()).limit(1))
            if row is None:
                raise Conflict(f"environment {environment_id} has no earlier map to restore")
        else:
            row = session.scalar(query.where(MapVersion.id == version)) if can_match(version) else None
            if row is None:
                raise NotFound(f"environment {environment_id} has no map version {version}")
        return MapDocument.model_validate(row.document)

    return replace_map(session, environment_id, MapChange.RESTORE, earlier, if_match=if_match)
