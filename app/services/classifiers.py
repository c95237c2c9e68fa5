"""Classifiers as data: stored as ``.npy`` arrays, the default installed at first start
(new ones come from training jobs, ``app.services.training``)."""

from __future__ import annotations

import io
import json

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.detection import DiscClassifier, load_default_classifier
from app.models import Classifier, ClassifierArray, Environment
from app.schemas import ClassifierOut
from app.services.errors import NotFound, get_or_404


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
    """The shipped default classifier, stored once (first start); returns its id."""
    existing = _default_row_id(session)
    if existing is not None:
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
