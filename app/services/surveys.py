"""Surveys: a calibration video (or a set of images) in, the environment's map out.

The upload is written straight into the job's upload folder as it arrives, under
server-chosen names (`SurveyUpload`, `app.services.uploads`), and checked in the request
as far as it can be: the container allow-list by magic bytes and the images' declared
sizes as the bytes come; once the file is whole, OpenCV can open it and read a first
frame, resolution and length within the limits, every Motion JPEG frame's declared size
within them too; images decodable. Then it is handed to a job.
The job, in a worker process, detects targets in the chosen frames with the
environment's classifier, tracks the walls' own texture through them (unless asked for
the cards alone; walls too plain to track get a warning), runs structure from motion
(`app.core.survey`) and stores the map in the same transaction that marks the job
succeeded: a failed or cancelled survey leaves the previous map untouched.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ValidationError
from sqlalchemy.orm import Session

from app.core.detection import DetectedTarget, Detector
from app.core.geometry import Camera, RollingShutter
from app.core.imagecodec import ImageError, decode_gray, peek_size
from app.core.features import FeatureTracker, exclusion_mask
from app.core.survey import FeatureObservations, SurveyError, survey
from app.core.survey.features import texture_warning
from app.schemas import CameraModel, JobOut, MapChange, MapDocument
from app.services import classifiers, environments, images, jobs
from app.services.errors import Invalid, TooLarge, UnsupportedMedia
from app.services.jobs import JobContext, JobKind, JobResult, JobRunner, job_handler
from app.services.uploads import FilePart, ImagePart, StoredFile
from app.settings import Settings

#: ISO base media (MP4, MOV) box types that may open a file.
_ISO_BOXES = (b"ftyp", b"moov", b"mdat", b"wide", b"free", b"skip", b"pnot")
#: Codecs OpenCV's FFmpeg backend reads reliably (FOURCC as OpenCV reports it).
ALLOWED_CODECS = frozenset({
    "avc1", "h264", "H264", "x264", "X264", "hev1", "hvc1", "hevc", "HEVC", "mp4v", "MP4V", "FMP4", "XVID", "xvid",
    "DIVX", "MJPG", "mjpg", "jpeg", "MJPEG", "vp09", "VP90", "av01", "AV01",
})
#: Codecs of Motion JPEG (FOURCC as OpenCV reports it): every packet is one JPEG, whose
#: size its header declares, so a frame is checked against the limits before it is decoded.
MJPEG_CODECS = frozenset({"MJPG", "mjpg", "jpeg", "MJPEG"})


@dataclass(frozen=True)
class VideoInfo:
    width: int
    height: int
    frames: int
    fps: float
    codec: str


def video_container(head: bytes) -> str | None:
    """'mp4' (also MOV), 'avi' or None from the first bytes of a file."""
    if len(head) >= 12 and head[4:8] in _ISO_BOXES:
        return "mp4"
    if len(head) >= 12 and head[:4] == b"RIFF" and head[8:12] == b"AVI ":
        return "avi"
    return None


def probe_video(path: Path, settings: Settings) -> VideoInfo:
    """Open a stored video with OpenCV and check it against the limits (4xx if not)."""
    with path.open("rb") as fh:
        head = fh.read(16)
    if video_container(head) is None:
        raise UnsupportedMedia("video: not an MP4, MOV or AVI file (unrecognised container)")
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        if not capture.isOpened():
            raise Invalid("video: cannot be opened (corrupt or truncated file?)")
        width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        frames = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        codec = _codec(capture)
        if width <= 0 or height <= 0:
            raise Invalid("video: no video stream")
        if width * height > settings.max_video_pixels:
            raise TooLarge(f"video: {width}x{height} exceeds the limit of {settings.max_video_pixels} pixels")
        if frames > settings.max_video_frames:
            raise TooLarge(f"video: {frames} frames exceed the limit of {settings.max_video_frames}")
        if codec and codec not in ALLOWED_CODECS:
            raise UnsupportedMedia(f"video: codec {codec!r} is not supported; use H.264, HEVC, MPEG-4 or MJPEG")
        ok, _ = capture.read()
        if not ok:
            raise Invalid("video: no frame could be decoded (corrupt or truncated file?)")
    finally:
        capture.release()
    if codec in MJPEG_CODECS:
        for index, size in _mjpeg_frame_sizes(path):
            if size is not None and size[0] * size[1] > settings.max_video_pixels:
                raise TooLarge(f"video: frame {index} is {size[0]}x{size[1]}, over the limit of "
                               f"{settings.max_video_pixels} pixels")
    return VideoInfo(width, height, frames, fps, codec)


def _codec(capture: cv2.VideoCapture) -> str:
    fourcc = int(capture.get(cv2.CAP_PROP_FOURCC))
    return "".join(chr((fourcc >> (8 * i)) & 0xFF) for i in range(4)).strip("\x00 ")


def _raw_packet(capture: cv2.VideoCapture) -> bytes | None:
    """The packet `grab` read, undecoded (the capture in raw mode: ``CAP_PROP_FORMAT`` -1)."""
    ok, packet = capture.retrieve()
    return packet.tobytes() if ok and packet is not None else None


def _declared_size(packet: bytes | None) -> tuple[int, int] | None:
    """(width, height) a Motion JPEG packet declares, None when it declares none."""
    try:
        return peek_size(packet) if packet else None
    except ImageError:
        return None


def _mjpeg_frame_sizes(path: Path) -> Iterator[tuple[int, tuple[int, int] | None]]:
    """(index, declared size) of every frame of a Motion JPEG video, read from its
    packets' headers: nothing is decoded."""
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        capture.set(cv2.CAP_PROP_FORMAT, -1)
        index = 0
        while capture.grab():
            yield index, _declared_size(_raw_packet(capture))
            index += 1
    finally:
        capture.release()


#: How far a survey's given intrinsics may differ in aspect ratio (width / height) from
#: the upload's, as a fraction: a resolution rounded to whole pixels (1920x1080 against
#: 854x480) differs by well under 1 %.
ASPECT_TOLERANCE = 0.01


def parse_intrinsics(text: str | None) -> CameraModel | None:
    """The ``intrinsics`` form field (JSON), or None when it is absent or blank."""
    if text is None or not text.strip():
        return None
    try:
        return CameraModel.model_validate(json.loads(text))
    except json.JSONDecodeError as exc:
        raise Invalid(f"intrinsics: not JSON ({exc.msg})") from None
    except ValidationError as exc:
        detail = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise Invalid(f"intrinsics: {detail}") from None


class SurveyParams(BaseModel):
    """A survey job: where its frames are, which of them to use, and what is known."""

    upload_dir: str
    source: Literal["video", "images"]
    video: str | None = None  # the stored video (source "video")
    video_frames: int | None = None  # its frame count as the container states it
    width: int
    height: int
    marker_size_m: float
    intrinsics: CameraModel | None  # a fixed camera, at the upload's size; None: calibrated by the survey
    max_frames: int
    classifier_id: int
    family: str
    max_pixels: int
    feature_tracks: bool = True  # track the scene's own points beside the cards
    readout_ms: float | None = None  # a rolling shutter's readout (None: a global shutter)
    readout_frames: float | None = None  # the same in video frames
    max_video_pixels: int | None = None  # largest frame of a video (None: max_pixels)


class VideoPart(StoredFile):
    """The survey's video: its container recognised from its first bytes, then probed
    whole (`probe_video`)."""

    def __init__(self, path: Path, settings: Settings) -> None:
        super().__init__(path, "video", settings.max_upload_bytes)
        self.settings = settings
        self.info: VideoInfo | None = None

    def check_head(self, head: bytes, *, final: bool) -> None:
        if video_container(head) is None:
            raise UnsupportedMedia("video: not an MP4, MOV or AVI file (unrecognised container)")

    def check_whole(self) -> None:
        self.info = probe_video(self.path, self.settings)


class SurveyUpload:
    """The files of a survey's form, written into the job's upload folder as they
    arrive (an `app.services.uploads.UploadTarget`): one ``video``, or ``images`` of one
    size stored as ``image_NNNNN.png|jpg``."""

    def __init__(self, folder: Path, settings: Settings, memory: images.MemoryBudget) -> None:
        self.folder = folder
        self.settings = settings
        self.memory = memory
        self.video: VideoPart | None = None
        self.images = 0
        self.image_size: tuple[int, int] | None = None

    def open_file(self, field: str) -> FilePart | None:
        if field not in ("video", "images"):
            return None
        if self.video is not None or (field == "video" and self.images):
            raise Invalid("give either a 'video' file or one or more 'images' files")
        if field == "video":
            self.video = VideoPart(self.folder / "video", self.settings)
            return self.video
        if self.images >= self.settings.max_survey_images:
            raise Invalid(f"images: at most {self.settings.max_survey_images} images per survey")
        index, self.images = self.images, self.images + 1
        return ImagePart(self.folder / f"image_{index:05d}", f"images[{index}]", self.settings, self.memory,
                         lambda _path, width, height: self._image_stored(index, width, height))

    def _image_stored(self, index: int, width: int, height: int) -> None:
        if self.image_size is None:
            self.image_size = (width, height)
        elif self.image_size != (width, height):
            first = self.image_size
            raise Invalid(f"images[{index}]: {width}x{height} differs from the first image's {first[0]}x{first[1]}; "
                          "one camera, one resolution")


def check_environment(session: Session, environment_id: int) -> None:
    """404 for an unknown environment: before a survey's upload is read."""
    environments.get_row(session, environment_id)


def submit_survey(
    session: Session,
    runner: JobRunner,
    settings: Settings,
    environment_id: int,
    upload: SurveyUpload,
    *,
    job_id: str,
    marker_size_m: float | None,
    intrinsics: str | None,
    max_frames: int | None,
    feature_tracks: bool = True,
    readout_ms: float | None = None,
) -> JobOut:
    """Queue the survey job of a stored upload (its folder is the job's). The caller
    removes the folder when this refuses it: no row is written then."""
    environment = environments.get_row(session, environment_id)
    video = upload.video.info if upload.video is not None else None
    if (video is None) == (upload.image_size is None):
        raise Invalid("give either a 'video' file or one or more 'images' files")
    if marker_size_m is not None and not (0.0 < marker_size_m <= 10.0):
        raise Invalid("marker_size_m: must be in (0, 10] metres")
    if max_frames is not None and not (2 <= max_frames <= settings.max_video_frames):
        raise Invalid(f"max_frames: must be between 2 and {settings.max_video_frames}")
    camera = parse_intrinsics(intrinsics)
    readout_frames = None
    if readout_ms is not None:
        if video is None:
            raise Invalid("readout_ms: a rolling shutter needs a video: the readout is counted in its frames")
        if not video.fps > 0:
            raise Invalid("readout_ms: the video does not state its frame rate")
        readout_frames = readout_ms * video.fps / 1000.0
        if not 0.0 < readout_frames <= 1.0:
            raise Invalid(f"readout_ms: must be more than 0 and at most a frame ({1000.0 / video.fps:.1f} ms at "
                          f"{video.fps:g} frames a second)")
    classifier_id = classifiers.for_environment(session, environment)
    if video is not None:
        assert upload.video is not None
        video_path, video_frames, width, height = str(upload.video.path), video.frames, video.width, video.height
    else:
        assert upload.image_size is not None
        video_path, video_frames, (width, height) = None, None, upload.image_size
    if camera is not None and (camera.width, camera.height) != (width, height):
        # The same lens at another resolution keeps the image's shape; intrinsics of
        # another shape are for another camera (or mistyped), not to be stretched.
        if abs(camera.width * height - camera.height * width) > ASPECT_TOLERANCE * camera.height * width:
            raise Invalid(f"intrinsics: given for {camera.width}x{camera.height}, whose shape differs from the "
                          f"upload's {width}x{height}; give them for this camera at any resolution of the "
                          "same shape")
        scaled = Camera.from_dict(camera.model_dump()).scaled_to(width, height)
        camera = CameraModel.model_validate(scaled.to_dict())
    params = SurveyParams(
        upload_dir=str(upload.folder), source="video" if video is not None else "images", video=video_path,
        video_frames=video_frames, width=width, height=height,
        marker_size_m=float(marker_size_m or environment.marker_size_m), intrinsics=camera,
        max_frames=int(max_frames or settings.survey_frames), classifier_id=classifier_id,
        family=environment.marker_family, max_pixels=settings.max_image_pixels, feature_tracks=feature_tracks,
        max_video_pixels=settings.max_video_pixels, readout_ms=readout_ms, readout_frames=readout_frames,
    )
    job = runner.submit(session, JobKind.SURVEY, params, environment_id=environment_id, job_id=job_id,
                        max_active=settings.max_queued_jobs)
    return jobs.job_out(job)


# --- in the worker process -----------------------------------------------------------


def _chosen(total: int, wanted: int) -> np.ndarray:
    """`wanted` frame indices spread evenly over `total` (all when fewer)."""
    if total <= wanted:
        return np.arange(total)
    return np.unique(np.round(np.linspace(0, total - 1, wanted)).astype(int))


def _video_total(params: SurveyParams, capture: cv2.VideoCapture) -> int:
    return int(params.video_frames or 0) or int(capture.get(cv2.CAP_PROP_FRAME_COUNT))


def frame_numbers(params: SurveyParams) -> np.ndarray:
    """Each frame the survey uses: its index in the video, or among the images."""
    if params.source == "video":
        assert params.video is not None
        capture = cv2.VideoCapture(params.video, cv2.CAP_FFMPEG)
        try:
            return _chosen(_video_total(params, capture), params.max_frames)
        finally:
            capture.release()
    return _chosen(len(list(Path(params.upload_dir).glob("image_*"))), params.max_frames)


def frame_count(params: SurveyParams) -> int:
    """How many frames the survey uses."""
    return len(frame_numbers(params))


def read_frames(params: SurveyParams, positions: range | None = None) -> Iterator[tuple[int, int, np.ndarray]]:
    """(position, count, greyscale frame) of the frames the survey uses, or of those at
    `positions` among them (a video is entered at the first one's frame)."""
    if params.source == "video":
        assert params.video is not None
        capture = cv2.VideoCapture(params.video, cv2.CAP_FFMPEG)
        try:
            # Motion JPEG is read packet by packet, undecoded, and each frame decoded
            # only once its header's size is known to be within the limit (FFmpeg
            # decodes any size a later frame declares, and OpenCV scales it to the first's).
            mjpeg = _codec(capture) in MJPEG_CODECS and capture.set(cv2.CAP_PROP_FORMAT, -1)
            chosen = _chosen(_video_total(params, capture), params.max_frames)
            positions = positions if positions is not None else range(len(chosen))
            if not positions:
                return
            wanted = {int(chosen[p]): p for p in positions}
            index = int(chosen[positions[0]])
            if index > 0:
                # OpenCV's FFmpeg reader seeks to the keyframe before and decodes up to
                # the frame asked for, so the pieces of a survey read the frames a
                # whole read would.
                capture.set(cv2.CAP_PROP_POS_FRAMES, index)
            last = int(chosen[positions[-1]])
            while index <= last and capture.grab():
                if index in wanted:
                    if mjpeg:
                        gray = _mjpeg_frame(params, index, _raw_packet(capture))
                    else:
                        ok, frame = capture.retrieve()
                        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if ok else None
                    if gray is not None:
                        yield wanted[index], len(chosen), gray
                index += 1
        finally:
            capture.release()
    else:
        files = sorted(Path(params.upload_dir).glob("image_*"))
        chosen = _chosen(len(files), params.max_frames)
        for position in positions if positions is not None else range(len(chosen)):
            yield position, len(chosen), decode_gray(files[int(chosen[position])].read_bytes(), params.max_pixels)


def _mjpeg_frame(params: SurveyParams, index: int, packet: bytes | None) -> np.ndarray | None:
    """Frame `index` of a Motion JPEG video in greyscale, from its packet, at the video's
    size; None when it cannot be read. A SurveyError, before anything is decoded, when
    its header declares more pixels than the limit."""
    size = _declared_size(packet)
    if packet is None or size is None:
        return None
    limit = params.max_video_pixels or params.max_pixels
    if size[0] * size[1] > limit:
        raise SurveyError(f"frame {index} of the video is {size[0]}x{size[1]} pixels, over the limit of {limit} "
                          f"(the video's first frame is {params.width}x{params.height}); every frame must be "
                          "within it")
    gray = cv2.imdecode(np.frombuffer(packet, np.uint8), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        return None
    if gray.shape != (params.height, params.width):
        # As FFmpeg's reader gives every frame: at the size of the first.
        gray = cv2.resize(gray, (params.width, params.height), interpolation=cv2.INTER_AREA)
    return gray


#: Frames in each piece of a survey's detection that a worker of the job engine takes:
#: about a second of work, so that the engine's cost per piece (a few ms) stays under 1 %.
FRAMES_PER_PIECE = 20


@dataclass(frozen=True)
class FramePiece:
    """Consecutive frames of a survey, detected by one worker."""

    params: SurveyParams
    positions: range


def detect_piece(detector: Detector, piece: FramePiece) -> list[tuple[int, list[DetectedTarget]]]:
    """(position, targets) of each frame of `piece` that could be read, in order (on a
    worker of the job engine)."""
    frames = read_frames(piece.params, piece.positions)
    return [(position, detector.detect(gray).targets) for position, _, gray in frames]


@job_handler(JobKind.SURVEY, SurveyParams)
def run_survey(params: SurveyParams, context: JobContext) -> JobResult:
    """Detect, reconstruct, store the map (see the module docstring)."""
    with context.sessions() as session:
        # Fitted disc centres: the survey averages many views of each disc, and the
        # centroid's small errors repeat from view to view (see app.core.detection.disc_fit).
        detector = Detector.for_survey(classifiers.load(session, params.classifier_id), params.family)
    numbers = frame_numbers(params)
    count = len(numbers)
    # The scene's own points are tracked frame after frame, after detection (the cards
    # left out: their discs are tracked as discs).
    detecting_share = 0.35 if params.feature_tracks else 0.5
    context.progress("detecting targets", 0.0)
    started = time.perf_counter()
    stage_s: dict[str, float] = {}

    def detected(finished: int, total: int) -> None:
        frames = min(finished * FRAMES_PER_PIECE, count)
        context.progress("detecting targets", detecting_share * finished / total, f"frame {frames} of {count}")

    pieces = [FramePiece(params, range(a, min(a + FRAMES_PER_PIECE, count))) for a in range(0, count, FRAMES_PER_PIECE)]
    by_position = dict(found for piece in context.fan_out(detect_piece, detector, pieces, detected) for found in piece)
    detections = [by_position[position] for position in sorted(by_position)]
    stage_s["detecting"] = time.perf_counter() - started
    tracker = None
    if params.feature_tracks:
        tracker = FeatureTracker()
        for position, _, gray in read_frames(params):
            if position not in by_position:
                continue  # (its frame could not be read for detection either)
            discs = np.array([t.discs for t in by_position[position]]).reshape(-1, 4, 2)
            tracker.add(gray, exclusion_mask(gray.shape, discs))
            context.progress("tracking features", detecting_share + (0.5 - detecting_share) * (position + 1) / count,
                             f"frame {position + 1} of {count}")
        stage_s["tracking"] = time.perf_counter() - started - stage_s["detecting"]
    found = sum(len(d) for d in detections)
    if found == 0:
        raise SurveyError(f"no target was found in any of the {len(detections)} frames: "
                          "check the video shows the printed targets, in focus and lit")
    intrinsics = Camera.from_dict(params.intrinsics.model_dump()) if params.intrinsics is not None else None

    def progress(stage: str, fraction: float) -> None:
        context.progress(stage, 0.5 + 0.48 * min(max(fraction, 0.0), 1.0))

    features = FeatureObservations.from_tracks(tracker.tracks()) if tracker is not None else None
    reconstructing = time.perf_counter()
    shutter = RollingShutter(params.readout_frames) if params.readout_frames is not None else None
    result = survey(detections, params.width, params.height, params.marker_size_m, intrinsics=intrinsics,
                    progress=progress, features=features, shutter=shutter,
                    frame_numbers=numbers[sorted(by_position)] if shutter is not None else None)
    stage_s["reconstructing"] = time.perf_counter() - reconstructing
    plain = texture_warning(features, len(detections)) if features is not None else None
    if plain is not None:
        result.map_warnings.append(plain)
        result.warnings.append(plain.message)
    document = MapDocument.model_validate(result.to_map_document(frame="survey", survey_job_id=context.job_id))
    summary = result.summary()
    # The calibration trajectory: the camera of each frame used (None: not registered).
    summary.update({"frames_used": len(detections), "detections": found, "feature_tracks": params.feature_tracks,
                    "readout_ms": params.readout_ms,
                    "stage_s": {stage: round(seconds, 3) for stage, seconds in stage_s.items()},
                    "trajectory": [pose.to_dict() if pose is not None else None for pose in result.trajectory]})
    assert context.environment_id is not None
    with context.finishing(summary) as session:
        environments.stage_map(session, context.environment_id, document, MapChange.SURVEY)
    return summary
