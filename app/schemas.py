"""Pydantic models of the API: what clients send and what they get back, over HTTP and
over the ``/track`` WebSocket. Importing this module has no side effects (the protocol and
configuration pages of the documentation are generated from it)."""

from __future__ import annotations

import json
import unicodedata
from datetime import UTC, datetime
from enum import IntEnum, StrEnum
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator, model_validator

#: Most keys a JSON object in a request may have: twice the fields of the largest request
#: model (every unknown key would cost an error of its own in the reply).
MAX_JSON_KEYS = 16
#: Most targets a map may hold: more than any marker family has ids (282).
MAX_MAP_TARGETS = 1000
#: Most errors a validation reply lists (the count says how many there were).
MAX_LISTED_ERRORS = 20


def load_json(data: bytes | str) -> Any:
    """Parse a request's JSON, refusing (ValueError) an object of more than
    `MAX_JSON_KEYS` keys as soon as the parser has read it: such a body would make
    validation build one error per key."""
    return json.loads(data, object_pairs_hook=_bounded_object)


def _bounded_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    if len(pairs) > MAX_JSON_KEYS:
        raise ValueError(f"an object has {len(pairs)} keys; at most {MAX_JSON_KEYS} are read")
    return dict(pairs)


def error_summary(errors: list[dict[str, Any]]) -> str:
    """Validation errors as one line for a person: "field: why; ..." for the first
    `MAX_LISTED_ERRORS`, then how many more (the input is never echoed)."""
    shown = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors[:MAX_LISTED_ERRORS])
    more = len(errors) - MAX_LISTED_ERRORS
    return shown + (f"; and {more} more errors" if more > 0 else "")


# JSON as Python parses it accepts NaN and Infinity; nothing stored may hold them.
Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNegativeFinite = Annotated[float, Field(allow_inf_nan=False, ge=0)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Row3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]


def _printable(value: str) -> str:
    # A name is shown in listings, logs and terminals: no NUL, no control characters
    # (a newline or an escape sequence in a name would forge or garble what shows it).
    bad = next((c for c in value if unicodedata.category(c) in ("Cc", "Cs")), None)
    if bad is not None:
        raise ValueError(f"must not contain control characters (found U+{ord(bad):04X})")
    return value


#: A name people give a thing (an environment, a classifier, an API key).
Name = Annotated[str, Field(min_length=1, max_length=200), AfterValidator(_printable)]


def _aware(value: datetime | None) -> datetime | None:
    # SQLite returns naive datetimes; everything is stored in UTC.
    if value is not None and value.tzinfo is None:
        return value.replace(tzinfo=UTC)
    return value


class Problem(BaseModel):
    """Error body of every 4xx/5xx reply."""

    detail: str


# --- environments -------------------------------------------------------------------


def _check_family(name: str) -> str:
    from app.core.markers import FAMILIES

    if name not in FAMILIES:
        raise ValueError(f"unknown marker family {name!r}; known: {', '.join(FAMILIES)}")
    return name


class EnvironmentCreate(BaseModel):
    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True)

    name: Name
    marker_size_m: float = Field(
        gt=0, le=10, allow_inf_nan=False, description="Side of the printed card in metres."
    )
    marker_family: str = Field("fido3x3", description="Code family of the printed cards.")
    classifier_id: int | None = Field(None, description="Classifier to detect with; default if null.")

    _family = field_validator("marker_family")(_check_family)


class EnvironmentUpdate(BaseModel):
    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True)

    name: Name | None = None
    marker_size_m: float | None = Field(None, gt=0, le=10, allow_inf_nan=False)
    classifier_id: int | None = None


class EnvironmentOut(BaseModel):
    id: int
    name: str
    marker_size_m: float
    marker_family: str
    classifier_id: int | None
    has_map: bool
    created_at: datetime
    updated_at: datetime

    _tz = field_validator("created_at", "updated_at")(_aware)


# --- maps ---------------------------------------------------------------------------


#: The numbers a camera may hold, checked where cameras enter (maps, survey intrinsics,
#: /track configs): far beyond any real lens, but not so far that the solvers' arithmetic
#: overflows (a focal length of 1e300 or 1e-300, or a distortion of 1e300, made the
#: pose solvers fail with a 500).
FOCAL_PX_RANGE = (1e-3, 1e7)
MAX_DISTORTION = 1e4
#: How far the principal point may lie outside the image, in image sizes.
PRINCIPAL_POINT_SPAN = 10.0
#: How far a map's discs may lie from its origin, metres.
MAX_COORDINATE_M = 1e6


class CameraModel(BaseModel):
    """OpenCV camera: ``K`` 3x3 and distortion ``[k1, k2, p1, p2, k3]``."""

    model_config = ConfigDict(extra="forbid")

    width: int = Field(gt=0, le=20000, description="Image width the intrinsics are for, px.")
    height: int = Field(gt=0, le=20000, description="Image height the intrinsics are for, px.")
    K: Annotated[list[Row3], Field(min_length=3, max_length=3, description=(
        "Camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels, the centre of the top-left pixel "
        "at (0, 0)."))]
    dist: Annotated[list[Finite], Field(min_length=5, max_length=5, description=(
        "OpenCV distortion coefficients [k1, k2, p1, p2, k3]."))]

    @model_validator(mode="after")
    def _camera_matrix(self) -> CameraModel:
        k = self.K
        if k[2] != [0.0, 0.0, 1.0] or k[1][0] != 0.0:
            raise ValueError("K must be upper triangular with last row [0, 0, 1]")
        if k[0][0] <= 0 or k[1][1] <= 0:
            raise ValueError("K must have positive focal lengths K[0][0] and K[1][1]")
        lo, hi = FOCAL_PX_RANGE
        if not (lo <= k[0][0] <= hi and lo <= k[1][1] <= hi):
            raise ValueError(f"K's focal lengths must lie in [{lo:g}, {hi:g}] px")
        if abs(k[0][1]) > k[0][0]:
            raise ValueError("K's skew K[0][1] must not exceed its focal length K[0][0]")
        span = PRINCIPAL_POINT_SPAN
        if abs(k[0][2]) > span * self.width or abs(k[1][2]) > span * self.height:
            raise ValueError(f"K's principal point must lie within {span:g} image sizes of the image")
        if any(abs(d) > MAX_DISTORTION for d in self.dist):
            raise ValueError(f"distortion coefficients must lie in [-{MAX_DISTORTION:g}, {MAX_DISTORTION:g}]")
        return self


Coordinate = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]


class MapTarget(BaseModel):
    model_config = ConfigDict(extra="forbid")

    id: int = Field(ge=0)
    discs: Annotated[list[Annotated[list[Coordinate], Field(min_length=3, max_length=3)]],
                     Field(min_length=4, max_length=4)] = Field(
        description="3D centres of discs 0..3 (top-left, top-right, bottom-right, bottom-left)."
    )
    std_m: Annotated[list[Annotated[float, Field(allow_inf_nan=False, ge=0, le=1000)]],
                     Field(min_length=4, max_length=4)] | None = Field(
        None, description="Each disc's position uncertainty from the survey (m, 1 sigma, relative to the map as a "
                          "whole); tracking adds it to the pose's covariance. None: the disc is taken as exact.")
    n_views: int | None = Field(None, ge=0)


class MapDocument(BaseModel):
    """The map of an environment: its camera and the 3D disc centres of every target (metres)."""

    model_config = ConfigDict(extra="forbid")

    frame: Literal["survey", "world"]
    units: Literal["m"] = "m"
    camera: CameraModel
    targets: list[MapTarget] = Field(max_length=MAX_MAP_TARGETS)
    rms_px: NonNegativeFinite | None = None
    survey_job_id: str | None = Field(None, max_length=32)

    @field_validator("targets")
    @classmethod
    def _unique_ids(cls, targets: list[MapTarget]) -> list[MapTarget]:
        seen: set[int] = set()
        for target in targets:
            if target.id in seen:
                raise ValueError(f"target id {target.id} appears more than once")
            seen.add(target.id)
        return targets


# --- markers ------------------------------------------------------------------------


class MarkerFamilyOut(BaseModel):
    name: str
    cells: int
    min_distance: int = Field(description="Least Hamming distance between codes in any rotation.")
    count: int = Field(description="Number of marker ids: 0 .. count-1.")


class MarkerCatalogue(BaseModel):
    default_family: str
    families: list[MarkerFamilyOut]


class MarkerLayoutOut(BaseModel):
    id: int
    family: str
    discs: list[list[float]] = Field(description="Disc centres in card units, card spans 0..1.")
    disc_radius: float
    code: list[list[int]]


# --- jobs and classifiers -----------------------------------------------------------


class JobStatus(StrEnum):
    """Where a job is: ``queued``, then ``running``, then one of ``succeeded``, ``failed`` or
    ``cancelled`` (a queued job may also end cancelled or failed without running)."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"


class JobOut(BaseModel):
    """A long piece of work: its stage and progress while it runs, its result after."""

    id: str
    kind: str
    status: JobStatus
    progress: float = Field(ge=0, le=1)
    stage: str
    message: str
    environment_id: int | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    result: dict[str, Any] | None
    error: str | None

    _tz = field_validator("created_at", "started_at", "finished_at")(_aware)


class ClassifierOut(BaseModel):
    """A trained disc detector: stage-1 parameters and condensed prototypes."""

    id: int
    name: str
    is_default: bool
    source: str
    training_job_id: str | None
    created_at: datetime
    training_stats: dict[str, Any]

    _tz = field_validator("created_at")(_aware)


# --- detection ----------------------------------------------------------------------


class DetectedTargetOut(BaseModel):
    id: int = Field(description="The target's id: the code it carries, in the environment's marker family.")
    discs: list[list[float]] = Field(
        description="Disc centres [u, v] in pixels: top-left, top-right, bottom-right, bottom-left of the card."
    )
    score: float = Field(description="Confidence 0..1: how clearly the target's weakest check passed.")


class DetectResponse(BaseModel):
    width: int
    height: int
    targets: list[DetectedTargetOut]
    candidates: list[list[float]] | None = Field(
        None, description="With ?candidates=true: every disc that passed the classifier, [u, v, radius, score]."
    )
    classifier_id: int
    timing_ms: dict[str, float]


class PoseOut(BaseModel):
    R: list[list[float]] = Field(description="Rotation, map to camera: x_cam = R @ X_map + t (3x3).")
    t: list[float] = Field(description="Translation, map to camera (m).")
    position: list[float] = Field(description="Camera centre in map coordinates, -R^T t (m).")
    reprojection_rms_px: float = Field(description="RMS reprojection error over the disc centres the pose rests on, px.")
    n_targets: int = Field(description="Targets the pose rests on (outliers excluded).")
    n_points: int = Field(description="Disc centres the pose rests on.")
    covariance_position: list[list[float]] = Field(
        description="Covariance of the camera centre (3x3, m^2): the noise level of the residuals, plus the "
                    "map's own uncertainty where the map gives std_m (each card off as a whole).")
    focal_px: float = Field(description="Focal length used: the camera's, or estimated when focal estimation is on (px).")
    method: str = Field(description="Pose method: nonlinear, posit, mean or single.")
    rejected_targets: list[int] = Field(description="Ids of targets refused as outliers.")


class LocateResponse(BaseModel):
    width: int = Field(description="Width of the image, px.")
    height: int = Field(description="Height of the image, px.")
    targets: list[DetectedTargetOut] = Field(description="Targets detected in the image.")
    pose: PoseOut | None = Field(description="The camera's pose in the map, or null (see pose_error).")
    pose_error: str | None = Field(None, description="Why there is no pose, when there is none.")
    timing_ms: dict[str, float] = Field(description=(
        "Where the time went, ms: decode, plan, the detector's stages (candidates, targets, detect, ...), pose, total."))


# --- tracking: the /track WebSocket ---------------------------------------------------
#
# The client sends frames as binary messages (JPEG, or PNG) and, whenever it likes, a
# `TrackConfig` as a text message. The server sends JSON text messages: one `TrackHello`
# first, then a `TrackFrame` per processed frame, a `TrackConfig` echo per accepted
# config, and a `TrackError` for each message it cannot use. A connection the server
# refuses gets one `TrackRefusal` and is closed.

PoseMethod = Literal["nonlinear", "posit", "mean", "single"]
#: Why a frame was scanned as it was: ``first`` (no pose yet), ``regions`` (only around
#: the predicted targets), ``periodic`` (every ``full_scan_every`` frames), ``lost`` (the
#: previous frame had no pose), ``fallback`` (the regions gave no pose, so the whole
#: frame was searched at once), ``wide`` (the regions would cover most of the frame),
#: ``stale`` (too many frames since the last pose), ``camera`` (the intrinsics or the
#: frame size changed), ``off`` (regions switched off by config).
ScanReason = Literal["first", "regions", "periodic", "lost", "fallback", "wide", "stale", "camera", "off"]


#: Codes of `TrackError` (the connection stays open).
TrackErrorCode = Literal["bad_message", "bad_config", "bad_frame", "frame_too_large", "rate_limited",
                         "internal_error"]
#: Codes of `TrackRefusal` (the connection is closed).
TrackRefusalCode = Literal["bad_request", "unknown_environment", "no_map", "too_many_connections", "idle"]


class TrackCloseCode(IntEnum):
    """WebSocket close codes of ``/track``."""

    GOING_AWAY = 1001  # the client sent nothing for ``track_idle_timeout_s``
    POLICY_VIOLATION = 1008  # a refused request: bad query, unknown environment, no map, missing API key
    SERVER_ERROR = 1011  # the connection failed on the server's side
    TRY_AGAIN_LATER = 1013  # the server already tracks ``max_track_connections`` connections


class TrackConfig(BaseModel):
    """Client -> server (text message): change how this connection's frames are processed.
    Fields left out take their defaults; the server echoes the whole config it now uses."""

    model_config = ConfigDict(extra="forbid")

    type: Literal["config"] = Field("config", description='Always "config".')
    method: PoseMethod = Field("nonlinear", description=(
        "Pose estimator: nonlinear (the paper's: reprojection error of every disc minimised with the full "
        "lens model); posit, mean (of single-target poses) and single (the largest target alone) for "
        "comparison."))
    estimate_focal: bool = Field(False, description="Free the focal length per frame (zoom lens).")
    intrinsics: CameraModel | None = Field(None, description="Override the map's camera (K, dist, size).")
    regions: bool = Field(True, description="Search only around the targets the previous poses predict "
                                            "(false: scan every whole frame).")
    full_scan_every: int = Field(30, ge=1, le=1_000_000,
                                 description="With regions, scan the whole frame at least every this many "
                                             "frames (finds targets the prediction misses).")


class TrackHello(BaseModel):
    """Server -> client, first: the connection is accepted and tracks against this map."""

    type: Literal["hello"] = Field("hello", description='Always "hello".')
    environment_id: int = Field(description="The environment whose map the poses refer to.")
    camera: CameraModel = Field(description="The map's camera; frames of another size are tracked with it "
                                            "scaled to their size.")
    targets: int = Field(description="Number of targets in the map.")


class TrackFrame(BaseModel):
    """Server -> client: the targets and the camera pose of one processed frame."""

    type: Literal["frame"] = Field("frame", description='Always "frame".')
    seq: int = Field(description="The frame's index among the binary messages of this connection, from 0.")
    width: int = Field(description="Width of the decoded frame in pixels.")
    height: int = Field(description="Height of the decoded frame in pixels.")
    targets: list[DetectedTargetOut] = Field(description="Targets found and identified in the frame.")
    pose: PoseOut | None = Field(description="The camera pose in map coordinates; null when the visible "
                                             "targets do not determine it.")
    pose_error: str | None = Field(description="Why there is no pose, when there is none.")
    timing_ms: dict[str, float] = Field(description=(
        "Server time per stage in milliseconds (decode, plan, candidates, targets, detect, pose, total); "
        "``regions`` counts the regions searched when the frame was scanned by regions."))
    dropped: int = Field(description="Frames received since the previous reply that newer frames replaced "
                                     "before they were processed (the newest frame is never dropped).")
    scan: Literal["full", "regions"] = Field(description="Whether the whole frame or only the predicted "
                                                         "regions were searched.")
    scan_reason: ScanReason = Field(description="Why the frame was scanned so (see `ScanReason`).")


class TrackError(BaseModel):
    """Server -> client: one message could not be used; the connection stays open."""

    type: Literal["error"] = Field("error", description='Always "error".')
    code: TrackErrorCode = Field(description=(
        "bad_message: a text message that is not a config; bad_config: a config that does not validate; "
        "bad_frame: a frame that cannot be decoded or is too small; frame_too_large: a frame over "
        "max_frame_bytes; rate_limited: frames over max_track_fps are being dropped (at most one such "
        "message a second); internal_error: the server failed on this frame."))
    message: str = Field(description="What was wrong, for a person.")
    seq: int | None = Field(description="The frame concerned (its index among the binary messages); null "
                                        "for text messages.")


class TrackRefusal(BaseModel):
    """Server -> client: the connection is refused and closed right after this message (close
    code 1013 for ``too_many_connections``, 1001 for ``idle``, else 1008)."""

    type: Literal["error"] = Field("error", description='Always "error".')
    code: TrackRefusalCode = Field(description=(
        "bad_request: environment_id is missing or not an integer; unknown_environment: no such environment; "
        "no_map: the environment has no map yet; too_many_connections: try again later; idle: the client sent "
        "no message for track_idle_timeout_s (connect again to go on)."))
    message: str = Field(description="Why, for a person.")

    @property
    def close_code(self) -> TrackCloseCode:
        """The WebSocket close code that follows this message."""
        if self.code == "too_many_connections":
            return TrackCloseCode.TRY_AGAIN_LATER
        if self.code == "idle":
            return TrackCloseCode.GOING_AWAY
        return TrackCloseCode.POLICY_VIOLATION


#: Every message the server sends on ``/track``.
TrackServerMessage = TrackHello | TrackFrame | TrackConfig | TrackError | TrackRefusal


# --- alignment ----------------------------------------------------------------------


class AlignmentPoint(BaseModel):
    model_config = ConfigDict(extra="forbid")

    target_id: int = Field(ge=0)
    disc: int = Field(
        ge=0, le=3, description="Disc index 0..3: top-left, top-right, bottom-right, bottom-left of the card."
    )
    world: Vec3 = Field(description="Known world position of that disc centre (m).")


class AlignmentRequest(BaseModel):
    """Either ``points`` (3 or more, not collinear) or ``origin_target_id``."""

    model_config = ConfigDict(extra="forbid")

    points: list[AlignmentPoint] | None = Field(None, max_length=4 * MAX_MAP_TARGETS)
    origin_target_id: int | None = Field(
        None, ge=0, description="This target's centre becomes the origin, its plane z = 0, x along disc 0 -> 1."
    )
    allow_scale: bool = Field(True, description="Fit the scale too (a similarity); false keeps the survey's scale.")

    @model_validator(mode="after")
    def _one_way(self) -> AlignmentRequest:
        if (self.points is None) == (self.origin_target_id is None):
            raise ValueError("give either points or origin_target_id")
        return self


class AlignmentResidual(BaseModel):
    target_id: int
    disc: int
    residual_m: float


class AlignmentResult(BaseModel):
    scale: float
    R: list[list[float]]
    t: list[float] = Field(description="x_world = scale * R @ x_map + t")
    residuals: list[AlignmentResidual]
    rms_m: float
    map: MapDocument


# --- health -------------------------------------------------------------------------


class Readiness(BaseModel):
    status: Literal["ready", "not ready"]
    database: str
    schema_revision: list[str]
    head_revision: list[str]


# --- API keys -----------------------------------------------------------------------


class ApiKeyCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: Name
    scopes: list[Literal["read", "track", "admin"]] = Field(min_length=1, max_length=3)


class ApiKeyOut(BaseModel):
    id: int
    name: str
    scopes: list[str]
    created_at: datetime
    revoked_at: datetime | None


class ApiKeyCreated(BaseModel):
    id: int
    name: str
    scopes: list[str]
    key: str = Field(description="The secret: shown once, only its hash is stored.")
