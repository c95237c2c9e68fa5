"""Classifiers as data: stored as ``.npy`` arrays, the default installed at first start,
new ones trained from a site's own images as a job (self-labelled)."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.learning.adapt import adapt_classifier
from app.core.detection import DiscClassifier, load_default_classifier
from app.core.imagecodec import PNG_MAGIC, decode_gray
from app.core.markers import FAMILIES
from app.models import Classifier, ClassifierArray
from app.schemas import ClassifierOut, JobOut
from app.services import jobs
from app.services.errors import Invalid, NotFound, ServiceError, get_or_404
from app.services.jobs import JobRunner
from app.settings import Settings


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


def install_default(session: Session) -> int:
    """The shipped default classifier, stored once (first start); returns its id."""
    existing = session.scalar(select(Classifier.id).where(Classifier.is_default.is_(True)))
    if existing is not None:
        return int(existing)
    row = add(session, load_default_classifier(), "default", "builtin", is_default=True)
    session.commit()
    return row.id


def default_id(session: Session) -> int:
    found = session.scalar(select(Classifier.id).where(Classifier.is_default.is_(True)).order_by(Classifier.id))
    if found is None:
        raise NotFound("no default classifier is installed")
    return int(found)


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


def run_training_job(context: Any) -> dict[str, Any]:
    """Job handler: adapt a classifier to a site's own images (see ``app.learning.training``)."""
    params = context.params
    image_dir = Path(params["upload_dir"])
    with context.sessions() as session:
        base = load(session, int(params["base_classifier_id"]))
    names = sorted(p.name for p in image_dir.iterdir())
    images = []
    for index, name in enumerate(names):
        images.append(decode_gray((image_dir / name).read_bytes(), max_pixels=int(params["max_pixels"])))
        context.progress("decoding", 0.05 * (index + 1) / len(names))

    def progress(stage: str, fraction: float) -> None:
        context.progress(stage, 0.05 + 0.9 * fraction)

    adapted = adapt_classifier(base, images, str(params["family"]), progress=progress)
    summary = {k: v for k, v in adapted.stats.items() if isinstance(v, (int, float, str, bool))}
    result: dict[str, Any] = {"images": len(images), "stats": summary}
    with context.finishing(result) as session:
        row = add(session, adapted, str(params["name"]), "trained", training_job_id=context.job_id)
        session.flush()
        result["classifier_id"] = row.id
    return result


def submit_training(
    session: Session,
    runner: JobRunner,
    settings: Settings,
    images: list[bytes],
    name: str,
    base_classifier_id: int | None,
    family: str,
) -> JobOut:
    """Check the upload whole, store the images under server-chosen names and queue
    the training job. Nothing is stored when any image is refused."""
    from app.services.detection import decode  # detection imports this module


    if family not in FAMILIES:
        raise Invalid(f"family: unknown marker family {family!r}; known: {', '.join(FAMILIES)}")
    if not images:
        raise Invalid("images: at least one image is required")
    if len(images) > settings.max_training_images:
        raise Invalid(f"images: at most {settings.max_training_images} images per training job")
    base = base_classifier_id if base_classifier_id is not None else default_id(session)
    get_row(session, base)
    for index, data in enumerate(images):
        try:
            decode(data, settings)
        except ServiceError as exc:
            exc.detail = f"images[{index}]: {exc.detail}"
            raise
    job_id = jobs.new_job_id()
    folder = jobs.uploads_dir(settings.data_dir, job_id)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        for index, data in enumerate(images):
            suffix = ".png" if data.startswith(PNG_MAGIC) else ".jpg"
            (folder / f"image_{index:04d}{suffix}").write_bytes(data)
        params = {"upload_dir": str(folder), "base_classifier_id": base, "name": name, "family": family,
                  "max_pixels": settings.max_image_pixels}
        job = jobs.create(session, "train_classifier", params, job_id=job_id, max_active=settings.max_queued_jobs)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    runner.submit(job.id, job.kind)
    return jobs.job_out(job)
