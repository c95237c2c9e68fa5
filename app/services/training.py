"""Training a classifier on a site's own images, as a job: targets the current detector
finds and verifies become positives, the candidates it rejects hard negatives
(``app.learning.adapt``); the adapted classifier is stored with the job's success."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel
from sqlalchemy.orm import Session

from app.core.imagecodec import decode_gray
from app.core.markers import FAMILIES
from app.learning.adapt import adapt_classifier
from app.schemas import JobOut
from app.services import classifiers, jobs
from app.services import images as image_service
from app.services.errors import Invalid
from app.services.jobs import JobContext, JobKind, JobResult, JobRunner, job_handler
from app.services.uploads import FilePart, ImagePart
from app.settings import Settings


class TrainingParams(BaseModel):
    """A training job: the stored images, the classifier to adapt and the new one's name."""

    upload_dir: str
    base_classifier_id: int
    name: str
    family: str
    max_pixels: int


class TrainingUpload:
    """The images of a training form, written into the job's upload folder as they
    arrive (an `app.services.uploads.UploadTarget`), as ``image_NNNN.png|jpg``."""

    def __init__(self, folder: Path, settings: Settings, memory: image_service.MemoryBudget) -> None:
        self.folder = folder
        self.settings = settings
        self.memory = memory
        self.images = 0
        self.stored = 0

    def open_file(self, field: str) -> FilePart | None:
        if field != "images":
            return None
        if self.images >= self.settings.max_training_images:
            raise Invalid(f"images: at most {self.settings.max_training_images} images per training job")
        index, self.images = self.images, self.images + 1
        return ImagePart(self.folder / f"image_{index:04d}", f"images[{index}]", self.settings, self.memory,
                         self._image_stored)

    def _image_stored(self, _path: Path, _width: int, _height: int) -> None:
        self.stored += 1


def submit_training(session: Session, runner: JobRunner, settings: Settings, upload: TrainingUpload, *, job_id: str,
                    name: str, base_classifier_id: int | None, family: str) -> JobOut:
    """Queue the training job of a stored upload (its folder is the job's; each image
    was decoded to check it as it was stored). The caller removes the folder when this
    refuses it: no row is written then."""
    if family not in FAMILIES:
        raise Invalid(f"family: unknown marker family {family!r}; known: {', '.join(FAMILIES)}")
    if not upload.stored:
        raise Invalid("images: at least one image is required")
    base = base_classifier_id if base_classifier_id is not None else classifiers.default_id(session)
    classifiers.get_row(session, base)
    params = TrainingParams(upload_dir=str(upload.folder), base_classifier_id=base, name=name, family=family,
                            max_pixels=settings.max_image_pixels)
    job = runner.submit(session, JobKind.TRAIN_CLASSIFIER, params, job_id=job_id, max_active=settings.max_queued_jobs)
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
