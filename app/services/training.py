"""Training a classifier on a site's own images, as a job: targets the current detector
finds and verifies become positives, the candidates it rejects hard negatives
(``app.learning.adapt``); the adapted classifier is stored with the job's success."""

from __future__ import annotations

import shutil
from pathlib import Path

from pydantic import BaseModel
from sqlalchemy.orm import Session

from app.core.imagecodec import PNG_MAGIC, decode_gray
from app.core.markers import FAMILIES
from app.learning.adapt import adapt_classifier
from app.schemas import JobOut
from app.services import classifiers, jobs
from app.services import images as image_service
from app.services.errors import Invalid, ServiceError
from app.services.jobs import JobContext, JobKind, JobResult, JobRunner, job_handler
from app.settings import Settings


class TrainingParams(BaseModel):
    """A training job: the stored images, the classifier to adapt and the new one's name."""

    upload_dir: str
    base_classifier_id: int
    name: str
    family: str
    max_pixels: int


def submit_training(session: Session, runner: JobRunner, settings: Settings, memory: image_service.MemoryBudget, *,
                    images: list[bytes], name: str, base_classifier_id: int | None, family: str) -> JobOut:
    """Check the upload whole, store the images under server-chosen names and queue
    the training job. Nothing is stored when any image is refused."""
    if family not in FAMILIES:
        raise Invalid(f"family: unknown marker family {family!r}; known: {', '.join(FAMILIES)}")
    if not images:
        raise Invalid("images: at least one image is required")
    if len(images) > settings.max_training_images:
        raise Invalid(f"images: at most {settings.max_training_images} images per training job")
    base = base_classifier_id if base_classifier_id is not None else classifiers.default_id(session)
    classifiers.get_row(session, base)
    for index, data in enumerate(images):
        try:
            with image_service.decoded(data, settings, memory, detect=False):
                pass
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
        params = TrainingParams(upload_dir=str(folder), base_classifier_id=base, name=name, family=family,
                                max_pixels=settings.max_image_pixels)
        job = runner.submit(session, JobKind.TRAIN_CLASSIFIER, params, job_id=job_id,
                            max_active=settings.max_queued_jobs)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return jobs.job_out(job)


@job_handler(JobKind.TRAIN_CLASSIFIER, TrainingParams)
def run_training(params: TrainingParams, context: JobContext) -> JobResult:
    """Adapt a classifier to a site's own images (see ``app.learning.adapt``) and store it."""
    image_dir = Path(params.upload_dir)
    with context.sessions() as session:
        base = classifiers.load(session, params.base_classifier_id)
    names = sorted(p.name for p in image_dir.iterdir())
    images = []
    for index, name in enumerate(names):
        images.append(decode_gray((image_dir / name).read_bytes(), max_pixels=params.max_pixels))
        context.progress("decoding", 0.05 * (index + 1) / len(names))

    def progress(stage: str, fraction: float) -> None:
        context.progress(stage, 0.05 + 0.9 * fraction)

    adapted = adapt_classifier(base, images, params.family, progress=progress)
    summary = {k: v for k, v in adapted.stats.items() if isinstance(v, (int, float, str, bool))}
    result: JobResult = {"images": len(images), "stats": summary}
    with context.finishing(result) as session:
        row = classifiers.add(session, adapted, params.name, "trained", training_job_id=context.job_id)
        session.flush()
        result["classifier_id"] = row.id
    return result
