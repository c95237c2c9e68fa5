"""Classifiers as data: stored as ``.npy`` arrays, the default installed at first start
(new ones come from training jobs, ``app.services.training``); a classifier nothing uses
may be deleted."""

from __future__ import annotations

import io
import json

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.detection import DiscClassifier, load_default_classifier
from app.db import lock_for_writing
from app.models import Classifier, ClassifierArray, Environment, Job
from app.schemas import ClassifierOut, JobStatus
from app.services.errors import Conflict, NotFound, get_or_404

#: The keys of a job's stored parameters that name a classifier it will load (the
#: survey's detector, the classifier a training job adapts).
_JOB_CLASSIFIER_PARAMS = ("classifier_id", "base_classifier_id")
#: How many environments a refusal names before it counts the rest.
_NAMED_ENVIRONMENTS = 10


def _to_npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array), allow_pickle=False)
    return buffer.getvalue()


def _from_npy(data: bytes) -> np.ndarray:
    return np.load(io.BytesIO(data), allow_pickle=False)


def to_out(classifier: Classifier) -> ClassifierOut:
    return ClassifierOut.model_validate(classifier, from_attributes=True)


def add(session: Session, classifier: DiscClassifier, name: str, source: str, is_default: bool = False,
        training_job_id: str | None = None) -> Classifier:
    """Stage a classifier row with its arrays (the caller commits)."""
    stats = json.loads(json.dumps(classifier.stats, default=float))  # plain JSON types only
    row = Classifier(name=name, source=source, is_default=is_default, training_stats=stats,
                     training_job_id=training_job_id)
    row.arrays = [ClassifierArray(name=key, npy=_to_npy(value)) for key, value in classifier.to_arrays().items()]
    session.add(row)
    return row


def _default_row_id(session: Session) -> int | None:
    found = session.scalar(select(Classifier.id).where(Classifier.is_default.is_(True)).order_by(Classifier.id))
    return None if found is None else int(found)


def install_default(session: Session) -> int:
    """The shipped default classifier, stored once (first start); returns its id. Servers
    starting together on one database store it once: the first to lock stores it, the
    others find it."""
    existing = _default_row_id(session)
    if existing is not None:
        return existing
    session.rollback()
    lock_for_writing(session, Classifier.__tablename__)
    existing = _default_row_id(session)
    if existing is not None:
        session.commit()
        return existing
    row = add(session, load_default_classifier(), "default", "builtin", is_default=True)
    session.commit()
    return row.id


def default_id(session: Session) -> int:
    found = _default_row_id(session)
    if found is None:
        raise NotFound("no default classifier is installed")
    return found


def for_environment(session: Session, environment: Environment) -> int:
    """The id of the classifier that detects in `environment`: its own, else the default."""
    return environment.classifier_id or default_id(session)


def get_row(session: Session, classifier_id: int) -> Classifier:
    return get_or_404(session, Classifier, classifier_id, "classifier")


def load(session: Session, classifier_id: int) -> DiscClassifier:
    row = get_row(session, classifier_id)
    arrays = {a.name: _from_npy(a.npy) for a in row.arrays}
    return DiscClassifier.from_arrays(arrays, dict(row.training_stats))


def list_all(session: Session) -> list[ClassifierOut]:
    return [to_out(c) for c in session.scalars(select(Classifier).order_by(Classifier.id))]


def get(session: Session, classifier_id: int) -> ClassifierOut:
    return to_out(get_row(session, classifier_id))


def delete(session: Session, classifier_id: int) -> None:
    """Delete a classifier and its arrays. Conflict (409) for the default classifier,
    for one that an environment detects with (naming the environments) and for one that
    a queued or running job will load; NotFound for an unknown id."""
    row = get_row(session, classifier_id)
    if row.is_default:
        raise Conflict(f"classifier {classifier_id} is the default classifier, which every environment without "
                       "a classifier of its own detects with; it cannot be deleted")
    users = session.execute(select(Environment.id, Environment.name).where(Environment.classifier_id == classifier_id)
                            .order_by(Environment.id)).all()
    if users:
        named = ", ".join(f"{env_id} ({name!r})" for env_id, name in users[:_NAMED_ENVIRONMENTS])
        more = len(users) - _NAMED_ENVIRONMENTS
        named += f" and {more} more" if more > 0 else ""
        raise Conflict(f"classifier {classifier_id} is used by environment{'s' if len(users) > 1 else ''} {named}; "
                       "give them another classifier (PATCH /environments/{id} with classifier_id) first")
    active = session.scalars(select(Job).where(Job.status.in_((JobStatus.QUEUED, JobStatus.RUNNING)))
                             .order_by(Job.created_at)).all()
    waiting = [job.id for job in active
               if any((job.params or {}).get(key) == classifier_id for key in _JOB_CLASSIFIER_PARAMS)]
    if waiting:
        raise Conflict(f"classifier {classifier_id} is used by job{'s' if len(waiting) > 1 else ''} "
                       f"{', '.join(waiting)}, queued or running; delete it once they end")
    session.delete(row)
    session.commit()
