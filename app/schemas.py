"""Pydantic models of the API: what clients send and what they get back, over HTTP and
over the ``/track`` WebSocket. Importing this module has no side effects (the protocol and
configuration pages of the documentation are generated from it)."""

from __future__ import annotations

import ipaddress
import json
import re
import unicodedata
from datetime import UTC, datetime
from enum import IntEnum, StrEnum
from typing import Annotated, Any, Literal

from pydantic import (AfterValidator, BaseModel, ConfigDict, Field, StringConstraints, ValidationInfo,
                      field_validator, model_validator)
from pydantic.json_schema import SkipJsonSchema, models_json_schema

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


# --- examples -----------------------------------------------------------------------
#
# The examples of the models below describe one consistent setting: 0.2 m cards of the
# fido3x3 family in a room, filmed with a 640x480 camera of focal length 823 px; card 7
# is in view about 1.4 m from the camera.

_EXAMPLE_JOB_ID = "3f6c0d2a9b8e4f7a8c1d2e3f4a5b6c7d"
_EXAMPLE_CAMERA: dict[str, Any] = {
    "width": 640,
    "height": 480,
    "K": [[823.4, 0.0, 318.7], [0.0, 823.4, 241.2], [0.0, 0.0, 1.0]],
    "dist": [-0.118, 0.094, 0.0, 0.0, 0.0],
}
_EXAMPLE_MAP_TARGETS: list[dict[str, Any]] = [
    {"id": 7, "discs": [[1.2031, 0.4078, 2.923], [1.3047, 0.4003, 2.8596], [1.3072, 0.5199, 2.8497],
                        [1.2056, 0.5273, 2.9131]],
     "std_m": [0.0009, 0.0008, 0.0009, 0.0011], "n_views": 42},
    {"id": 12, "discs": [[2.4105, 0.3822, 3.1054], [2.5301, 0.3817, 3.1102], [2.5296, 0.5018, 3.1097],
                         [2.41, 0.5023, 3.1049]],
     "std_m": [0.0014, 0.0013, 0.0015, 0.0014], "n_views": 17},
]
_EXAMPLE_MAP: dict[str, Any] = {
    "frame": "survey", "units": "m", "camera": _EXAMPLE_CAMERA, "targets": _EXAMPLE_MAP_TARGETS, "rms_px": 0.31,
    "survey_job_id": _EXAMPLE_JOB_ID,
}
_EXAMPLE_DETECTED: dict[str, Any] = {
    "id": 7, "discs": [[297.41, 170.36], [365.12, 168.21], [365.48, 241.03], [297.02, 241.39]], "score": 0.94,
    "read_margin": 412.6,
}
_EXAMPLE_R = [[0.9776, -0.0381, -0.207], [0.0214, 0.9964, -0.0825], [0.2094, 0.0762, 0.9749]]
_EXAMPLE_POSE: dict[str, Any] = {
    "R": _EXAMPLE_R,
    "t": [-0.5918, -0.311, -1.742],
    "position": [0.95, 0.42, 1.55],
    "reprojection_rms_px": 0.18,
    "n_targets": 2,
    "n_points": 8,
    "covariance_position": [[4.1e-06, 2.0e-07, -1.1e-06], [2.0e-07, 3.2e-06, 4.0e-07], [-1.1e-06, 4.0e-07, 9.8e-06]],
    "focal_px": 823.4,
    "method": "nonlinear",
    "rejected_targets": [],
    "ambiguous": False,
    "tilt_from_track": False,
}
_EXAMPLE_DETECT_MS = {"candidates": 6.12, "targets": 3.27, "targets.group": 0.91, "targets.verify": 1.48,
                      "targets.refine": 0.52, "targets.identify": 0.21, "targets.complete": 0.15, "detect": 9.46}
_EXAMPLE_WARNING = (
    "card 12: seen in 2 registered frames only (fewer than 3), from 2.4 m, over 9 degrees of viewing directions: "
    "film it again from 1-2 m, walking past it so you see it from at least 15 degrees apart (a step of 0.5 m "
    "sideways at 2 m), with other cards in the same shot")


def _examples(*examples: dict[str, Any]) -> dict[str, Any]:
    """A model's ``json_schema_extra``: its examples, as the OpenAPI document shows them."""
    return {"examples": list(examples)}


# --- errors -------------------------------------------------------------------------


class Problem(BaseModel):
    """Error body of every 4xx/5xx reply."""

    model_config = ConfigDict(json_schema_extra=_examples({"detail": "environment 9 not found"}))

    detail: str = Field(description="What went wrong, for a person.")


class FieldError(BaseModel):
    """One part of a request that did not validate."""

    loc: list[str | int] = Field(description=(
        "Where: ``body``, ``query``, ``path`` or ``header``, then the field's path within it "
        '(e.g. ["body", "marker_size_m"]).'))
    msg: str = Field(description="Why, for a person.")
    type: str = Field(description="The kind of error, e.g. missing, greater_than, json_invalid.")


class ValidationProblem(Problem):
    """Error body of a 422 reply: ``detail`` says what is wrong; when the request did not
    match its schema, ``errors`` lists each field (the first 20) and ``detail`` sums them
    up."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "detail": "body.marker_size_m: Input should be greater than 0",
        "errors": [{"loc": ["body", "marker_size_m"], "msg": "Input should be greater than 0", "type": "greater_than"}],
    }))

    errors: list[FieldError] = Field(default_factory=list, description=(
        "The fields that did not validate, the first 20; empty (or absent) when the request was well formed but "
        "does not fit the stored state (a target id outside the marker family, an image too small to search)."))


# --- environments -------------------------------------------------------------------


def _check_family(name: str) -> str:
    from app.core.markers import FAMILIES

    if name not in FAMILIES:
        raise ValueError(f"unknown marker family {name!r}; known: {', '.join(FAMILIES)}")
    return name


class EnvironmentCreate(BaseModel):
    """A new environment: a place, the printed size and code family of its cards."""

    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True, json_schema_extra=_examples(
        {"name": "studio", "marker_size_m": 0.2, "marker_family": "fido3x3", "classifier_id": None}))

    name: Name = Field(description="A name for people (1-200 characters, no control characters).")
    marker_size_m: float = Field(
        gt=0, le=10, allow_inf_nan=False, description="Side of the printed card in metres."
    )
    marker_family: str = Field("fido3x3", description="Code family of the printed cards.")
    classifier_id: int | None = Field(None, description="Classifier to detect with; default if null.")

    _family = field_validator("marker_family")(_check_family)


class EnvironmentUpdate(BaseModel):
    """Changes to an environment: the fields given are changed, the others kept."""

    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True, json_schema_extra=_examples(
        {"name": "studio B"}, {"classifier_id": 2}))

    name: Name | None = Field(None, description="A new name.")
    marker_size_m: float | None = Field(None, gt=0, le=10, allow_inf_nan=False,
                                        description="A new side of the printed card in metres.")
    classifier_id: int | None = Field(None, description="Another classifier to detect with; null: the default.")


class EnvironmentOut(BaseModel):
    """An environment: a place with its cards, and whether it has a map yet."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "id": 1, "name": "studio", "marker_size_m": 0.2, "marker_family": "fido3x3", "classifier_id": None,
        "has_map": True, "created_at": "2026-11-20T09:12:31Z", "updated_at": "2026-11-20T10:03:02Z"}))

    id: int = Field(description="The environment's id (never reused).")
    name: str = Field(description="Its name.")
    marker_size_m: float = Field(description="Side of the printed cards in metres.")
    marker_family: str = Field(description="Code family of the printed cards.")
    classifier_id: int | None = Field(description="The classifier it detects with; null: the default classifier.")
    has_map: bool = Field(description="Whether it has a map (surveyed or imported): tracking needs one.")
    created_at: datetime = Field(description="When it was created (UTC).")
    updated_at: datetime = Field(description="When it or its map last changed (UTC).")

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

    model_config = ConfigDict(extra="forbid", json_schema_extra=_examples(_EXAMPLE_CAMERA))

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
    """One target of a map: the 3D centres of its four discs."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_examples(_EXAMPLE_MAP_TARGETS[0]))

    id: int = Field(ge=0, description="The target's id: the code its card carries, in the environment's family.")
    discs: Annotated[list[Annotated[list[Coordinate], Field(min_length=3, max_length=3)]],
                     Field(min_length=4, max_length=4)] = Field(
        description="3D centres of discs 0..3 (top-left, top-right, bottom-right, bottom-left)."
    )
    std_m: Annotated[list[Annotated[float, Field(allow_inf_nan=False, ge=0, le=1000)]],
                     Field(min_length=4, max_length=4)] | None = Field(
        None, description="Each disc's position uncertainty from the survey (m, 1 sigma, relative to the map as a "
                          "whole); tracking adds it to the pose's covariance. None: the disc is taken as exact.")
    n_views: int | None = Field(None, ge=0, description="Registered survey frames the target was seen in; null "
                                                        "when the map did not come from a survey.")


class MapDocument(BaseModel):
    """The map of an environment: its camera and the 3D disc centres of every target (metres)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_examples(_EXAMPLE_MAP))

    frame: Literal["survey", "world"] = Field(description=(
        "survey: the survey's own frame (metric, its origin and axes arbitrary); world: aligned to the world "
        "(by an alignment, or measured so)."))
    units: Literal["m"] = Field("m", description='Always "m": every coordinate is in metres.')
    camera: CameraModel = Field(description="The camera of the survey; tracking uses it, scaled to each frame's "
                                            "size, unless a connection gives its own.")
    targets: list[MapTarget] = Field(max_length=MAX_MAP_TARGETS, description="Every target of the map, each id "
                                                                             "once.")
    rms_px: NonNegativeFinite | None = Field(None, description=(
        "The survey's reprojection RMS over every disc observation it kept, px; null for a map measured otherwise."))
    survey_job_id: Annotated[str, AfterValidator(_printable)] | None = Field(
        None, max_length=32, description="The survey job that made the map, or null (no control characters).")

    @field_validator("targets")
    @classmethod
    def _unique_ids(cls, targets: list[MapTarget]) -> list[MapTarget]:
        seen: set[int] = set()
        for target in targets:
            if target.id in seen:
                raise ValueError(f"target id {target.id} appears more than once")
            seen.add(target.id)
        return targets


class MapChange(StrEnum):
    """What replaced a map: each change keeps the map it replaced as a version."""

    IMPORT = "import"  # PUT /environments/{id}/map
    SURVEY = "survey"  # a survey job that succeeded
    ALIGNMENT = "alignment"  # POST /environments/{id}/alignment
    RESTORE = "restore"  # POST /environments/{id}/map/restore


class MapVersionOut(BaseModel):
    """An earlier map of an environment: what it was, and what replaced it when."""

    model_config = ConfigDict(json_schema_extra=_examples(
        {"version": 3, "frame": "survey", "n_targets": 24, "survey_job_id": "5f0c2d9e8b7a4c1d9e2f3a4b5c6d7e8f",
         "revision": 4, "replaced_by": "alignment", "replaced_at": "2026-11-27T10:15:00Z"}))

    version: int = Field(description="The version's number: give it to POST .../map/restore to restore it.")
    frame: Literal["survey", "world"] = Field(description="The frame of that map: the survey's own, or aligned.")
    n_targets: int = Field(description="Targets in that map.")
    survey_job_id: str | None = Field(description="The survey job that made that map, or null.")
    revision: int | None = Field(None, description=(
        "The revision that map had (its ETag while it was the map); null for a map kept by a service that did not "
        "count revisions."))
    replaced_by: MapChange = Field(description="The change that replaced it.")
    replaced_at: datetime = Field(description="When it was replaced.")

    _tz = field_validator("replaced_at")(_aware)


class MapRestoreRequest(BaseModel):
    """Which earlier map to restore (`GET .../map/versions` lists them); by default the
    one the last change replaced."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_examples({"version": 3}, {}))

    version: int | None = Field(None, ge=1, description="The version to restore; null: the newest.")


# --- markers ------------------------------------------------------------------------


class MarkerFamilyOut(BaseModel):
    """A code family: how many cards it has and how far apart their codes are."""

    name: str = Field(description="The family's name, as an environment's marker_family gives it.")
    cells: int = Field(description="Cells per side of the card's code (3: a 3x3 code).")
    min_distance: int = Field(description="Least Hamming distance between codes in any rotation.")
    count: int = Field(description="Number of marker ids: 0 .. count-1.")


class MarkerCatalogue(BaseModel):
    """The marker families and the default one."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "default_family": "fido3x3",
        "families": [{"name": "fido3x3", "cells": 3, "min_distance": 2, "count": 60},
                     {"name": "fido4x4", "cells": 4, "min_distance": 4, "count": 282}],
    }))

    default_family: str = Field(description="The family used where none is given.")
    families: list[MarkerFamilyOut] = Field(description="Every family.")


class MarkerLayoutOut(BaseModel):
    """One card's layout in card units: the card spans 0..1 on both axes, y down."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "id": 7, "family": "fido3x3", "discs": [[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]], "disc_radius": 0.125,
        "code": [[1, 0, 1], [0, 1, 0], [0, 0, 0]]}))

    id: int = Field(description="The card's id within its family.")
    family: str = Field(description="The card's code family.")
    discs: list[list[float]] = Field(description="Disc centres in card units, card spans 0..1.")
    disc_radius: float = Field(description="Radius of every disc, card units.")
    code: list[list[int]] = Field(description="The code's cells row by row, upright: 1 black, 0 white.")


# --- jobs and classifiers -----------------------------------------------------------


class JobStatus(StrEnum):
    """Where a job is: ``queued``, then ``running``, then one of ``succeeded``, ``failed`` or
    ``cancelled`` (a queued job may also end cancelled or failed without running)."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"


class IntrinsicsStd(BaseModel):
    """One standard deviation of each intrinsic the survey calibrated, from the final
    bundle adjustment (null where the covariance does not determine it)."""

    focal_px: float | None = Field(description="Of the focal length, px.")
    principal_point_px: Annotated[list[float | None], Field(min_length=2, max_length=2)] = Field(
        description="Of the principal point's x and y, px.")
    k1: float | None = Field(description="Of the radial distortion coefficient k1.")
    k2: float | None = Field(description="Of the radial distortion coefficient k2.")


class CardWarningKind(StrEnum):
    """What is weak about a part of a surveyed map."""

    FEW_VIEWS = "few views"  # seen in too few registered frames
    NARROW = "narrow"  # seen over too narrow a range of directions
    NOT_SURVEYED = "not surveyed"  # detected but not in the map
    DISCONNECTED = "disconnected"  # in the map, but never seen together with the rest
    PURE_PAN = "pure pan"  # the camera only turned: no baseline anywhere
    MISREAD = "probable misread"  # an id read a few times, weakly or on another card: left out of the map
    PLAIN_WALLS = "plain walls"  # too little texture to track: the map rests on the cards alone
    UNCERTAIN = "uncertain"  # in the map, placed too uncertainly to trust (reached through card-less frames)


class CardWarning(BaseModel):
    """A survey warning about some of the cards, and what to film to fix it."""

    kind: CardWarningKind = Field(description=(
        "few views: seen in too few registered frames; narrow: seen over too narrow a range of directions; "
        "not surveyed: detected but not in the map; disconnected: never seen together with the rest of the map; "
        "pure pan: the camera only turned on one spot; probable misread: an id read in a few frames only, "
        "each read weak or on another card's place, taken for a misread of another card's code and left out "
        "of the map (nothing to film again); plain walls: the walls had too little texture for feature tracks, "
        "so the map rests on the cards alone (names no card); uncertain: in the map but placed more uncertainly "
        "than 1 cm (1 sigma), reached only through frames with no other card in view."))
    target_ids: list[int] = Field(description="The ids of the cards it is about.")
    message: str = Field(description="The warning for a person (also one of the result's warnings).")
    frames: list[int] = Field(default_factory=list, description=(
        "The frames it is about, as numbered in the trajectory: for a probable misread, those the id was read in."))


class FramePose(BaseModel):
    """A camera pose of the survey's trajectory, in the map's frame (metres)."""

    R: list[list[float]] = Field(description="Rotation, map to camera: x_cam = R @ X_map + t (3x3).")
    t: list[float] = Field(description="Translation, map to camera (m).")
    position: list[float] = Field(description="Camera centre in map coordinates, -R^T t (m).")


_EXAMPLE_SURVEY_RESULT: dict[str, Any] = {
    "n_frames": 4, "n_registered": 3, "n_targets": 2, "rms_px": 0.31, "focal_px": 823.4,
    "principal_point": [318.7, 241.2], "dist": [-0.118, 0.094, 0.0, 0.0, 0.0],
    "intrinsics_std": {"focal_px": 2.7, "principal_point_px": [1.9, 1.6], "k1": 0.004, "k2": 0.011},
    "correlation_time": 1.2,
    "warnings": [_EXAMPLE_WARNING],
    "card_warnings": [{"kind": "few views", "target_ids": [12], "message": _EXAMPLE_WARNING, "frames": []}],
    "timing_s": {"intrinsics": 0.4, "initial": 0.2, "register": 3.1, "bundle": 5.8, "scale": 0.1,
                 "covariance": 0.9},
    "frames_used": 4, "detections": 7, "feature_tracks": True, "readout_ms": None,
    "stage_s": {"detecting": 0.21, "tracking": 0.12, "reconstructing": 0.35},
    "trajectory": [
        {"R": _EXAMPLE_R, "t": [-0.5918, -0.311, -1.742], "position": [0.95, 0.42, 1.55]},
        {"R": [[0.9921, -0.0312, -0.1215], [0.0215, 0.9968, -0.0803], [0.1236, 0.0771, 0.9893]],
         "t": [-0.7804, -0.3327, -1.6321], "position": [0.9995, 0.4321, 1.5238]},
        None,
        {"R": [[0.9997, -0.0201, -0.0148], [0.0189, 0.9973, -0.0712], [0.0162, 0.0709, 0.9974]],
         "t": [-1.0523, -0.3605, -1.5307], "position": [1.0981, 0.4531, 1.4848]},
    ],
}


class SurveyResult(BaseModel):
    """The result of a survey job (kind ``survey``): the calibrated camera, how well the
    map fits, the warnings, and the camera's path through the frames used."""

    model_config = ConfigDict(json_schema_extra=_examples(_EXAMPLE_SURVEY_RESULT))

    n_frames: int = Field(description="Frames the reconstruction used: those read (frames_used), unless it "
                                      "subsampled them.")
    n_registered: int = Field(description="Frames whose camera pose the survey found.")
    n_targets: int = Field(description="Targets in the map.")
    rms_px: float = Field(description="Reprojection RMS over every disc observation kept, px.")
    focal_px: float = Field(description="Focal length, px (given, or calibrated by the survey).")
    principal_point: Annotated[list[float], Field(min_length=2, max_length=2)] = Field(
        description="Principal point [cx, cy], px.")
    dist: Annotated[list[float], Field(min_length=5, max_length=5)] = Field(
        description="Distortion coefficients [k1, k2, p1, p2, k3].")
    intrinsics_std: IntrinsicsStd | None = Field(None, description=(
        "How well the survey determined the camera; null when the intrinsics were given."))
    correlation_time: float = Field(1.0, ge=1.0, description=(
        "How many consecutive observations of a disc count as one independent measurement: their errors' "
        "integrated autocorrelation time, from the final adjustment's residuals. The survey's uncertainties "
        "(intrinsics_std, each disc's std_m) are widened by it; 1 when the frames' errors are independent."))
    warnings: list[str] = Field(description="Every warning, for a person: weak cards, a lens known poorly.")
    card_warnings: list[CardWarning] = Field(default_factory=list, description=(
        "The warnings about parts of the map, with their kind and the cards they name."))
    timing_s: dict[str, float] = Field(description=(
        "Seconds per stage of the reconstruction: intrinsics, initial, register, bundle, scale, covariance."))
    frames_used: int = Field(description="Frames read from the upload, evenly spaced (at most max_frames).")
    detections: int = Field(description="Targets detected over those frames, counted once per frame.")
    feature_tracks: bool = Field(False, description=(
        "Whether the scene's own points were tracked beside the cards (the survey's default; false when it was "
        "asked for the cards alone)."))
    readout_ms: float | None = Field(None, description=(
        "The rolling shutter's readout the survey modelled, ms (null: a global shutter)."))
    stage_s: dict[str, float] = Field(default_factory=dict, description=(
        "Seconds each stage took: `detecting` (every frame's targets, spread over the job engine's workers), "
        "`tracking` (the scene's points, with feature_tracks), `reconstructing` (structure from motion)."))
    trajectory: list[FramePose | None] = Field(default_factory=list, description=(
        "The camera of each frame read, in order; null for a frame not registered."))


_EXAMPLE_TRAINING_RESULT: dict[str, Any] = {
    "classifier_id": 2, "images": 3,
    "stats": {"seed": 0, "site_images": 3, "site_targets_verified": 7, "site_positive_windows": 28,
              "site_negative_windows": 412, "condensation_prototypes": 1843, "condensation_added": 96,
              "site_stage2_disc_window_accept_before": 0.82, "site_stage2_disc_window_accept_after": 0.97,
              "site_targets_before": 7, "site_targets_after": 9},
}


class TrainingResult(BaseModel):
    """The result of a classifier training job (kind ``train_classifier``): the new
    classifier and how it did on the site's images."""

    model_config = ConfigDict(json_schema_extra=_examples(_EXAMPLE_TRAINING_RESULT))

    classifier_id: int = Field(description="The new classifier: choose it for an environment by this id.")
    images: int = Field(description="The site images it was trained on.")
    stats: dict[str, bool | int | float | str] = Field(description=(
        "Counts and rates of the training: windows labelled on the site images, prototypes added, the share of "
        "disc and false windows accepted before and after, targets found before and after."))


#: The result model of each kind of job, by the kind's name (``app.services.jobs.JobKind``).
RESULT_MODELS: dict[str, type[SurveyResult] | type[TrainingResult]] = {
    "survey": SurveyResult,
    "train_classifier": TrainingResult,
}


class JobOut(BaseModel):
    """A long piece of work: its stage and progress while it runs, its result after."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "id": _EXAMPLE_JOB_ID, "kind": "survey", "status": "succeeded", "progress": 1.0, "stage": "done",
        "message": "done", "environment_id": 1, "created_at": "2026-11-20T09:20:04Z",
        "started_at": "2026-11-20T09:20:05Z", "finished_at": "2026-11-20T09:21:47Z",
        "result": _EXAMPLE_SURVEY_RESULT,
        "error": None,
    }, {
        "id": "8d1e5b7c2a0f4e6d9b3c5a7e1f2d4c6b", "kind": "train_classifier", "status": "running", "progress": 0.35,
        "stage": "labelling site images", "message": "", "environment_id": None,
        "created_at": "2026-11-20T11:02:40Z", "started_at": "2026-11-20T11:02:41Z", "finished_at": None,
        "result": None, "error": None,
    }))

    id: str = Field(description="The job's id; its status is at /jobs/{id}.")
    kind: str = Field(description="survey or train_classifier.")
    status: JobStatus = Field(description="queued, running, succeeded, failed or cancelled.")
    progress: float = Field(ge=0, le=1, description="How far it is, 0..1.")
    stage: str = Field(description="What it is doing now (detecting targets, bundle, ...; done when it succeeded).")
    message: str = Field(description="More about the stage, for a person (e.g. frame 12 of 120).")
    environment_id: int | None = Field(description="The environment it works on (a survey's); null for others.")
    created_at: datetime = Field(description="When it was submitted (UTC).")
    started_at: datetime | None = Field(description="When a worker started it (UTC); null while queued.")
    finished_at: datetime | None = Field(description="When it ended (UTC); null while queued or running.")
    attempt: int = Field(0, ge=0, description=(
        "Which run of the job this is: 1 once started, more when a worker died and it ran again."))
    worker: str | None = Field(None, description="The job engine's worker running (or that ran) it.")
    heartbeat_at: datetime | None = Field(None, description=(
        "When its worker last said it was alive (UTC); a running job silent for job_lease_s is failed."))
    # A kind without a model of its own (there is none in the service) keeps its plain
    # result rather than failing to show: left out of the schema.
    result: SurveyResult | TrainingResult | SkipJsonSchema[dict[str, Any]] | None = Field(description=(
        "Once it succeeded: a SurveyResult for kind survey, a TrainingResult for kind train_classifier; "
        "null before, and after a failure or a cancellation."))
    error: str | None = Field(description="Why it failed, for a person; null unless it failed.")

    _tz = field_validator("created_at", "started_at", "finished_at")(_aware)

    @field_validator("result", mode="before")
    @classmethod
    def _result_of_kind(cls, value: Any, info: ValidationInfo) -> Any:
        # No tag in the stored result says which model it is: the job's kind does.
        model = RESULT_MODELS.get(str(info.data.get("kind")))
        if model is not None and isinstance(value, dict):
            return model.model_validate(value)
        return value


class ClassifierOut(BaseModel):
    """A trained disc detector: stage-1 parameters and condensed prototypes."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "id": 2, "name": "site A", "is_default": False, "source": "trained",
        "training_job_id": "8d1e5b7c2a0f4e6d9b3c5a7e1f2d4c6b", "created_at": "2026-11-20T11:06:12Z",
        "training_stats": _EXAMPLE_TRAINING_RESULT["stats"],
    }))

    id: int = Field(description="The classifier's id, as an environment's classifier_id gives it.")
    name: str = Field(description="Its name.")
    is_default: bool = Field(description="Whether it is the default, which environments without a classifier of "
                                         "their own detect with.")
    source: str = Field(description="builtin: shipped with the service; trained: made by a training job.")
    training_job_id: str | None = Field(description="The training job that made it; null for the builtin one.")
    created_at: datetime = Field(description="When it was stored (UTC).")
    training_stats: dict[str, Any] = Field(description="How it was trained and how it scored (keys depend on "
                                                       "its source).")

    _tz = field_validator("created_at")(_aware)


# --- detection ----------------------------------------------------------------------


class DetectedTargetOut(BaseModel):
    """One target found in an image."""

    model_config = ConfigDict(json_schema_extra=_examples(_EXAMPLE_DETECTED))

    id: int = Field(description="The target's id: the code it carries, in the environment's marker family.")
    discs: list[list[float]] = Field(
        description="Disc centres [u, v] in pixels: top-left, top-right, bottom-right, bottom-left of the card."
    )
    score: float = Field(description="Confidence 0..1: how clearly the target's weakest check passed.")
    read_margin: float | None = Field(None, description=(
        "How clearly the code was read: how much worse the best other printed pattern (another code, this "
        "code turned, or a pattern one cell from a code) fits the card's pixels than this code, in units of "
        "the pixels' residual variance (twice the log-likelihood ratio). Codes are accepted from 12; a few "
        "hundred is a clear read. None when not known."))


class DetectResponse(BaseModel):
    """The targets in one image (and, on request, every candidate disc)."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "width": 640, "height": 480, "targets": [_EXAMPLE_DETECTED],
        "candidates": [[297.41, 170.36, 8.6, 0.21], [365.12, 168.21, 8.4, 0.19], [365.48, 241.03, 8.9, 0.2],
                       [297.02, 241.39, 9.1, 0.22], [112.6, 403.2, 3.1, 0.12]],
        "classifier_id": 1, "timing_ms": _EXAMPLE_DETECT_MS,
    }))

    width: int = Field(description="Width of the image, px.")
    height: int = Field(description="Height of the image, px.")
    targets: list[DetectedTargetOut] = Field(description="Targets found and identified, by id.")
    candidates: list[list[float]] | None = Field(
        None, description="With ?candidates=true: every disc that passed the classifier, [u, v, radius, score]."
    )
    classifier_id: int = Field(description="The classifier that detected them.")
    timing_ms: dict[str, float] = Field(description=(
        "Milliseconds: candidates, targets (and its stages targets.group, targets.verify, targets.refine, "
        "targets.identify, targets.complete), and detect, the whole."))


#: Client conventions of a pose (docs/conventions.md): ``opencv`` (the map frame as it is,
#: camera x right, y down, looking down +z), ``opengl`` (WebXR, ARKit, three.js: y up,
#: camera looking down -z), ``unity`` (left-handed, y up), ``unreal`` (left-handed, z up,
#: centimetres). The y-up and z-up frames take the map's z as up.
PoseFrame = Literal["opencv", "opengl", "unity", "unreal"]
_EXAMPLE_FRAME_POSE: dict[str, Any] = {
    "frame": "unreal", "unit": "cm",
    "matrix": [[1.0, 0.0, 0.0, 100.0], [0.0, 1.0, 0.0, -200.0], [0.0, 0.0, 1.0, 150.0], [0.0, 0.0, 0.0, 1.0]],
    "quaternion_xyzw": [0.0, 0.0, 0.0, 1.0], "position": [100.0, -200.0, 150.0]}


class ClientPose(BaseModel):
    """A camera pose as a client engine takes it: the camera's transform in that engine's world."""

    model_config = ConfigDict(json_schema_extra=_examples(_EXAMPLE_FRAME_POSE))

    frame: PoseFrame = Field(description="The convention: opencv, opengl, unity or unreal.")
    matrix: list[list[float]] = Field(description=(
        "Camera to world, 4x4, row-major (rows of the matrix): its columns are the camera's axes in that "
        "convention and its position, in the convention's world and unit."))
    quaternion_xyzw: list[float] = Field(description="The matrix's rotation as a unit quaternion [x, y, z, w], w >= 0.")
    position: list[float] = Field(description="The camera's position in the convention's world, in `unit`.")
    unit: Literal["m", "cm"] = Field(description="The unit of `position` and of the matrix's last column.")


class FilteredPoseOut(BaseModel):
    """/track: the pose smoothed and/or predicted ahead, per the connection's config."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "R": _EXAMPLE_R, "t": [-0.5918, -0.311, -1.742], "position": [0.95, 0.42, 1.55], "smoothed": True,
        "predict_ms": 40.0, "frame_pose": _EXAMPLE_FRAME_POSE}))

    R: list[list[float]] = Field(description="Rotation, map to camera (3x3), as in `pose`.")
    t: list[float] = Field(description="Translation, map to camera (m).")
    position: list[float] = Field(description="Camera centre in map coordinates (m).")
    smoothed: bool = Field(description="Whether the One Euro filter smoothed it (config `smoothing`).")
    predict_ms: float = Field(description="How far ahead of the frame's arrival it was predicted, ms (0: not).")
    frame_pose: ClientPose = Field(description="The same pose in the convention of config `frame`.")


class PoseOut(BaseModel):
    """A camera pose in a map, and how well the targets determine it."""

    model_config = ConfigDict(json_schema_extra=_examples(_EXAMPLE_POSE))

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
    ambiguous: bool = Field(False, description=(
        "The pose rests on one card whose two tilts both fit its discs (seen small or from afar): the other "
        "tilt, a pose far off, fitted almost as well."))
    tilt_from_track: bool = Field(False, description=(
        "/track only: of a lone card's two tilts, the one consistent with the connection's previous poses was "
        "taken over the one with the lower reprojection error (a flip avoided; config `tilt`)."))
    frame_pose: ClientPose | None = Field(None, description=(
        "/track only: the same pose in the client convention of the connection's config `frame` "
        "(docs/conventions.md)."))


class LocateResponse(BaseModel):
    """The targets in one image and the camera's pose in the environment's map."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "width": 640, "height": 480, "targets": [_EXAMPLE_DETECTED], "pose": _EXAMPLE_POSE, "pose_error": None,
        "timing_ms": {"decode": 1.93, "plan": 0.04, **_EXAMPLE_DETECT_MS, "pose": 1.12, "total": 12.71},
    }))

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
                         "freed", "internal_error"]
#: Codes of `TrackRefusal` (the connection is closed).
TrackRefusalCode = Literal["bad_request", "unknown_environment", "no_map", "too_many_connections", "idle",
                           "client_connections", "too_many_requests", "key_revoked"]
#: Refusals after which the client may try again later (close code 1013).
TRY_AGAIN_REFUSALS = frozenset({"too_many_connections", "client_connections", "too_many_requests"})


class TrackCloseCode(IntEnum):
    """WebSocket close codes of ``/track``."""

    GOING_AWAY = 1001  # the client sent nothing for ``track_idle_timeout_s``
    POLICY_VIOLATION = 1008  # a refused request: bad query, unknown environment, no map, missing API key
    SERVER_ERROR = 1011  # the connection failed on the server's side
    TRY_AGAIN_LATER = 1013  # the service, or this client, is at a limit (`TRY_AGAIN_REFUSALS`)


#: Longest prediction a /track client may ask for, ms: beyond a few frames a constant
#: velocity guess is worse than the last pose.
MAX_PREDICT_MS = 500.0


class Smoothing(BaseModel):
    """The One Euro filter of a /track connection (Casiez et al. 2012): a low-pass whose
    cut-off rises with the speed, so a still camera is smoothed hard and a moving one
    lags little."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_examples(
        {"min_cutoff_hz": 1.0, "beta": 20.0, "beta_rotation": 5.0}))

    min_cutoff_hz: float = Field(1.0, gt=0, le=1000, description="Cut-off of a still camera, Hz (lower: smoother).")
    beta: float = Field(20.0, ge=0, le=1e6, description="Rise of the cut-off with speed, Hz per m/s (higher: "
                                                         "less lag in motion).")
    beta_rotation: float = Field(5.0, ge=0, le=1e6, description="Rise of the orientation's cut-off with angular "
                                                                 "speed, Hz per rad/s.")


class RollingShutterModel(BaseModel):
    """A camera whose rows are read one after another (a phone's, most webcams'): each
    row sees the room from where the camera was when it was read. Given, /track fits
    the camera's motion through the readout with each pose (docs/protocol.md)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_examples({"readout_ms": 20.0, "frame_rate": 30.0}))

    readout_ms: float = Field(gt=0, le=1000, description="Time from the first row's read to the last's, ms "
                                                         "(phones: 10-30 ms).")
    frame_rate: float = Field(gt=0, le=1000, description="Frames a second the client sends: one step of the "
                                                         "frames' seq is 1 / frame_rate seconds.")

    @model_validator(mode="after")
    def _within_a_frame(self) -> RollingShutterModel:
        if self.readout_ms * self.frame_rate > 1000.0:
            raise ValueError(f"a readout of {self.readout_ms:g} ms is longer than a frame at {self.frame_rate:g} "
                             "frames a second")
        return self


#: One label of a host name (RFC 1123): letters, digits and inner hyphens, 1-63 characters.
_HOST_LABEL = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?")
#: A last label the system's resolver reads as a number ("127.1", "0x7f000001"): the
#: address it stands for would be checked only once resolved, so such names are refused.
_NUMERIC_LABEL = re.compile(r"[0-9]+|0[xX][0-9A-Fa-f]*")


def _host_name(value: str) -> str:
    try:
        address = ipaddress.ip_address(value)
    except ValueError:
        address = None
    if address is not None:
        if "%" in value:
            raise ValueError("must be an IP address without a zone (%...)")
        return value
    labels = value.split(".")
    if (len(value) > 253 or not all(_HOST_LABEL.fullmatch(label) for label in labels)
            or _NUMERIC_LABEL.fullmatch(labels[-1])):
        raise ValueError("must be an IP address (v4, or v6 without brackets) or a host name: dot-separated "
                         "labels of 1-63 letters, digits and inner hyphens (RFC 1123), not ending in a number")
    return value


#: A host name or an IP address (v4, or v6 without brackets), as a UDP receiver is named.
#: Whitespace is refused, not stripped: " x" is not taken for "x".
HostName = Annotated[str, StringConstraints(strip_whitespace=False, min_length=1, max_length=253),
                     AfterValidator(_host_name)]


class FreeDOutput(BaseModel):
    """An environment's FreeD output: every /track connection of the environment sends its
    poses as FreeD D1 packets to this receiver (docs/freed.md)."""

    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True, json_schema_extra=_examples(
        {"host": "192.168.1.40", "port": 40000, "camera_id": 1, "enabled": True}))

    host: HostName = Field(description=(
        "Receiver's host name or IP address (the machine running Unreal Engine, Aximmetry, ...)."))
    port: int = Field(ge=1, le=65535, description="Receiver's UDP port.")
    camera_id: int = Field(1, ge=0, le=255, description="The camera id byte of the packets, unless a connection "
                                                        "sets its own.")
    enabled: bool = Field(True, description="Whether connections send (false keeps the settings, sends nothing).")


class FreeDConnection(BaseModel):
    """Where one /track connection sends its FreeD packets. Host and port left out are the
    environment's FreeD output's."""

    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True, json_schema_extra=_examples(
        {"camera_id": 2}, {"host": "192.168.1.40", "port": 40000, "camera_id": 1}, {"enabled": False}))

    host: HostName | None = Field(None, description="Receiver's host name or IP address.")
    port: int | None = Field(None, ge=1, le=65535, description="Receiver's UDP port.")
    camera_id: int = Field(1, ge=0, le=255, description="The camera id byte of the packets.")
    enabled: bool = Field(True, description="false: this connection sends no FreeD, even where the environment "
                                            "has an output (a preview client beside the studio camera).")


class TrackConfig(BaseModel):
    """Client -> server (text message): change how this connection's frames are processed.
    Fields left out take their defaults; the server echoes the whole config it now uses."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_examples(
        {"type": "config", "method": "nonlinear", "estimate_focal": False, "intrinsics": None, "regions": True,
         "full_scan_every": 30},
        {"type": "config", "intrinsics": _EXAMPLE_CAMERA}))

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
    frame: PoseFrame = Field("opencv", description=(
        "The client convention of `pose.frame_pose` and `filtered.frame_pose`: opencv, opengl (WebXR, ARKit), "
        "unity or unreal (docs/conventions.md)."))
    tilt: Literal["track", "residual"] = Field("track", description=(
        "How a lone card's two tilts are told apart when both fit: track (the one consistent with this "
        "connection's previous poses) or residual (the lower reprojection error alone)."))
    smoothing: Smoothing | None = Field(None, description=(
        "Smooth the poses with a One Euro filter (null: off); the result is the reply's `filtered`."))
    predict_ms: float = Field(0.0, ge=0, le=MAX_PREDICT_MS, description=(
        "Predict the pose this many ms after the frame's arrival at the server (constant velocity), to hide "
        "the latency between a frame and its use; the result is the reply's `filtered`."))
    rolling_shutter: RollingShutterModel | None = Field(None, description=(
        "The camera's rolling shutter: each pose is then the middle row's, fitted with the camera's motion "
        "through the readout. Null: a global shutter (every row read at once)."))
    freed: FreeDConnection | None = Field(None, description=(
        "Send each pose as a FreeD D1 packet over UDP (docs/freed.md): to this connection's own receiver, or "
        "with the environment's FreeD output's host and port and this camera id. Null: the environment's "
        "FreeD output, if it has one."))


#: Why a `TrackHello` is sent: ``connected`` (the first message of a connection),
#: ``map_changed`` (the environment's map was replaced while the connection was open: a
#: survey, an import, an alignment, a restore), ``classifier_changed`` (its classifier was).
TrackHelloReason = Literal["connected", "map_changed", "classifier_changed"]


class TrackHello(BaseModel):
    """Server -> client, first: the connection is accepted and tracks against this map.
    Sent again, with ``reason`` ``map_changed`` or ``classifier_changed``, when the
    environment's map or classifier changes while the connection is open: the replies
    after it are posed against the new map, with the connection's tracking state (its
    previous poses, its smoothing filter) started afresh."""

    model_config = ConfigDict(json_schema_extra=_examples(
        {"type": "hello", "environment_id": 1, "camera": _EXAMPLE_CAMERA, "targets": 24, "map_frame": "world",
         "reason": "connected"}))

    type: Literal["hello"] = Field("hello", description='Always "hello".')
    environment_id: int = Field(description="The environment whose map the poses refer to.")
    camera: CameraModel = Field(description="The map's camera; frames of another size are tracked with it "
                                            "scaled to their size.")
    targets: int = Field(description="Number of targets in the map.")
    map_frame: Literal["survey", "world"] = Field("world", description=(
        "The map's frame. In a survey's own frame nothing is up: align the map (docs/map-format.md) before "
        "using poses in the y-up or z-up client conventions or FreeD's pan and tilt."))
    reason: TrackHelloReason = Field("connected", description=(
        "connected: the connection's first message; map_changed or classifier_changed: the environment's map "
        "or classifier changed while the connection was open, and the following replies use the new one."))


class TrackFrame(BaseModel):
    """Server -> client: the targets and the camera pose of one processed frame."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "type": "frame", "seq": 42, "width": 640, "height": 480, "targets": [_EXAMPLE_DETECTED],
        "pose": _EXAMPLE_POSE, "pose_error": None,
        "timing_ms": {"decode": 1.88, "plan": 0.06, "candidates": 2.31, "targets": 1.42, "detect": 3.9, "regions": 2,
                      "pose": 1.05, "total": 7.12},
        "dropped": 0, "scan": "regions", "scan_reason": "regions",
    }))

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
        "``regions`` counts the regions searched when the frame was scanned by regions; ``reduction`` (2 or 4) "
        "says the JPEG was decoded at 1/2 or 1/4 of its size (HD frames whose discs the track predicts "
        "large enough); ``freed`` is the time from the frame's arrival to its FreeD packet."))
    dropped: int = Field(description="Frames received since the previous reply that newer frames replaced "
                                     "before they were processed (the newest frame is never dropped).")
    scan: Literal["full", "regions"] = Field(description="Whether the whole frame or only the predicted "
                                                         "regions were searched.")
    scan_reason: ScanReason = Field(description="Why the frame was scanned so (see `ScanReason`).")
    filtered: FilteredPoseOut | None = Field(None, description=(
        "The pose smoothed and/or predicted, when config `smoothing` or `predict_ms` asks for it and the frame "
        "has a pose; this is the pose FreeD sends then."))


class TrackError(BaseModel):
    """Server -> client: one message could not be used; the connection stays open."""

    model_config = ConfigDict(json_schema_extra=_examples(
        {"type": "error", "code": "bad_frame", "message": "frame 43: not a JPEG or PNG image (unknown file signature)",
         "seq": 43}))

    type: Literal["error"] = Field("error", description='Always "error".')
    code: TrackErrorCode = Field(description=(
        "bad_message: a text message that is not a config; bad_config: a config that does not validate; "
        "bad_frame: a frame that cannot be decoded or is too small; frame_too_large: a frame over "
        "max_frame_bytes; rate_limited: frames over max_track_fps are being dropped (at most one such "
        "message a second); freed: a FreeD packet could not be sent, or the FreeD config cannot be used (at "
        "most one such message a second); internal_error: the server failed on this frame."))
    message: str = Field(description="What was wrong, for a person.")
    seq: int | None = Field(description="The frame concerned (its index among the binary messages); null "
                                        "for text messages.")


class TrackRefusal(BaseModel):
    """Server -> client: the connection is refused and closed right after this message (close
    code 1013 for ``too_many_connections``, ``client_connections`` and ``too_many_requests``,
    1001 for ``idle``, else 1008)."""

    model_config = ConfigDict(json_schema_extra=_examples(
        {"type": "error", "code": "no_map",
         "message": "environment 1 has no map yet: run a survey or PUT one"}))

    type: Literal["error"] = Field("error", description='Always "error".')
    code: TrackRefusalCode = Field(description=(
        "bad_request: environment_id is missing or not an integer; unknown_environment: no such environment; "
        "no_map: the environment has no map yet; too_many_connections: try again later; idle: the client sent "
        "no message for track_idle_timeout_s (connect again to go on); client_connections: this client address or "
        "API key already holds its share of the connections (max_track_connections_per_address, _per_key); "
        "too_many_requests: this client address or API key opens connections faster than its rate "
        "(track_open_rate_per_address, _per_key), try again after retry_after_s; key_revoked: the connection's "
        "API key was revoked while it was open."))
    message: str = Field(description="Why, for a person.")
    retry_after_s: float | None = Field(None, exclude_if=lambda value: value is None, description=(
        "too_many_requests only: seconds until this client may open a connection again (the field is absent "
        "otherwise)."))

    @property
    def close_code(self) -> TrackCloseCode:
        """The WebSocket close code that follows this message."""
        if self.code in TRY_AGAIN_REFUSALS:
            return TrackCloseCode.TRY_AGAIN_LATER
        if self.code == "idle":
            return TrackCloseCode.GOING_AWAY
        return TrackCloseCode.POLICY_VIOLATION


#: Every message the server sends on ``/track``.
TrackServerMessage = TrackHello | TrackFrame | TrackConfig | TrackError | TrackRefusal
#: The ``/track`` messages, both ways, as the OpenAPI document lists them.
TRACK_MESSAGES: tuple[type[BaseModel], ...] = (TrackConfig, TrackHello, TrackFrame, TrackError, TrackRefusal)


def track_message_schemas() -> dict[str, dict[str, Any]]:
    """The JSON schemas of the ``/track`` messages and of the models they contain, by
    model name, referring to each other as ``#/components/schemas/<name>``: ready to merge
    into an OpenAPI document's ``components.schemas`` (FastAPI lists no WebSocket route
    there). The parts they share with HTTP replies (`CameraModel`, `DetectedTargetOut`,
    `PoseOut`) have the same schemas as there."""
    # The client's message as it is validated, the server's as they are written.
    modes = [(model, "validation" if model is TrackConfig else "serialization") for model in TRACK_MESSAGES]
    _, top = models_json_schema(modes, ref_template="#/components/schemas/{model}")
    return dict(top["$defs"])


def complete_openapi(document: dict[str, Any]) -> dict[str, Any]:
    """The application's OpenAPI document made whole, changed in place and returned (for
    the application's ``openapi()``; calling it again changes nothing):

    - the ``/track`` messages (`track_message_schemas`) join ``components.schemas``;
    - each model's examples are put back as the model gives them: FastAPI's encoder of
      the document drops every null value, even inside examples, which left examples
      without their required null fields (a job's ``error``) that the model refuses.
    """
    schemas = document.setdefault("components", {}).setdefault("schemas", {})
    if any(model.__name__ not in schemas for model in TRACK_MESSAGES):
        for name, schema in track_message_schemas().items():
            schemas.setdefault(name, schema)
    for name, schema in schemas.items():
        model = globals().get(name)
        if isinstance(model, type) and issubclass(model, BaseModel) and "examples" in schema:
            extra = model.model_config.get("json_schema_extra")
            if isinstance(extra, dict) and "examples" in extra:
                schema["examples"] = json.loads(json.dumps(extra["examples"]))
    return document


# --- alignment ----------------------------------------------------------------------


class AlignmentPoint(BaseModel):
    """A disc whose position in the world is known."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_examples(
        {"target_id": 7, "disc": 0, "world": [2.1, 0.0, 1.45]}))

    target_id: int = Field(ge=0, description="The id of the disc's target, in the map.")
    disc: int = Field(
        ge=0, le=3, description="Disc index 0..3: top-left, top-right, bottom-right, bottom-left of the card."
    )
    world: Vec3 = Field(description="Known world position of that disc centre (m).")


class AlignmentRequest(BaseModel):
    """Either ``points`` (3 or more, not collinear) or ``origin_target_id``."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_examples(
        {"points": [{"target_id": 7, "disc": 0, "world": [2.1, 0.0, 1.45]},
                    {"target_id": 7, "disc": 1, "world": [2.22, 0.0, 1.45]},
                    {"target_id": 12, "disc": 3, "world": [3.9, 0.35, 1.33]}],
         "allow_scale": False},
        {"origin_target_id": 7}))

    points: list[AlignmentPoint] | None = Field(None, max_length=4 * MAX_MAP_TARGETS, description=(
        "Discs with known world positions: three or more, not all on one line."))
    origin_target_id: int | None = Field(
        None, ge=0, description="This target's centre becomes the origin, its plane z = 0, x along disc 0 -> 1."
    )
    allow_scale: bool = Field(False, description=(
        "Fit the scale too (a similarity). A surveyed map is metric already (its scale comes from the card size): "
        "leave it false unless the map's scale is known to be wrong."))
    force: bool = Field(False, description=(
        "Store the fit even when it is refused: residuals beyond the tolerance, or a fitted scale far from 1. "
        "The map it replaces can be restored (POST .../map/restore)."))

    @model_validator(mode="after")
    def _one_way(self) -> AlignmentRequest:
        if (self.points is None) == (self.origin_target_id is None):
            raise ValueError("give either points or origin_target_id")
        return self


class AlignmentResidual(BaseModel):
    """How far one given disc lies from its known world position after the fit."""

    target_id: int = Field(description="The disc's target.")
    disc: int = Field(description="The disc, 0..3.")
    residual_m: float = Field(description="Distance between the disc moved into the world and its given "
                                          "position (m).")


class AlignmentResult(BaseModel):
    """The transform from the map's frame to the world, how well it fits, and the map
    moved into the world (stored in place of the old one)."""

    model_config = ConfigDict(json_schema_extra=_examples({
        "scale": 1.0021, "R": [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], "t": [-0.83, 1.79, 1.86],
        "residuals": [{"target_id": 7, "disc": 0, "residual_m": 0.0021},
                      {"target_id": 7, "disc": 1, "residual_m": 0.0017},
                      {"target_id": 12, "disc": 3, "residual_m": 0.0024}],
        "rms_m": 0.0021,
        "map": {**_EXAMPLE_MAP, "frame": "world", "targets": [
            {**_EXAMPLE_MAP_TARGETS[0], "discs": [[2.1, -0.4, 1.45], [2.04, -0.5, 1.45], [2.03, -0.5, 1.33],
                                                  [2.09, -0.4, 1.33]]}]},
    }))

    scale: float = Field(description="Map metres to world units (1 with allow_scale false).")
    R: list[list[float]] = Field(description="Rotation, map to world (3x3).")
    t: list[float] = Field(description="x_world = scale * R @ x_map + t")
    residuals: list[AlignmentResidual] = Field(description="Each given point's residual; empty for an origin "
                                                           "target.")
    rms_m: float = Field(description="RMS of the residuals (m); 0 for an origin target.")
    map: MapDocument = Field(description="The map in the world frame, now the environment's map.")


# --- health -------------------------------------------------------------------------


class Readiness(BaseModel):
    """Whether the service can serve: its database answers and is at the newest schema, and
    the detector's kernels are compiled."""

    model_config = ConfigDict(json_schema_extra=_examples(
        {"status": "ready", "reason": None, "database": "ok", "schema_revision": ["0002"], "head_revision": ["0002"]},
        {"status": "not ready", "reason": "compiling the detector's kernels", "database": "ok",
         "schema_revision": ["0002"], "head_revision": ["0002"]}))

    status: Literal["ready", "not ready"] = Field(description="ready, or not ready (503).")
    reason: str | None = Field(None, description="Why it is not ready, for a person; null when it is.")
    database: str = Field(description="ok, or why the database cannot be reached.")
    schema_revision: list[str] = Field(description="The database schema's migration revision.")
    head_revision: list[str] = Field(description="The newest migration revision this version knows.")


# --- API keys -----------------------------------------------------------------------

#: What an API key may do (docs/security.md): ``read`` every GET but of /keys, ``track``
#: /track, /detect and /locate, ``admin`` everything.
Scope = Literal["read", "track", "admin"]


class ApiKeyCreate(BaseModel):
    """A new API key: its name and what it may do."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_examples(
        {"name": "stage camera 1", "scopes": ["read", "track"]}))

    name: Name = Field(description="A name for people (1-200 characters, no control characters).")
    scopes: list[Scope] = Field(min_length=1, max_length=3, description=(
        "read: every GET but of /keys; track: /track, /detect and /locate; admin: everything, /keys included."))


class ApiKeyOut(BaseModel):
    """An API key as listed: never its secret."""

    model_config = ConfigDict(json_schema_extra=_examples(
        {"id": 3, "name": "stage camera 1", "scopes": ["read", "track"], "created_at": "2026-11-20T08:55:10Z",
         "revoked_at": None}))

    id: int = Field(description="The key's id.")
    name: str = Field(description="Its name.")
    scopes: list[str] = Field(description="What it may do: read, track, admin.")
    created_at: datetime = Field(description="When it was created (UTC).")
    revoked_at: datetime | None = Field(description="When it was revoked (UTC); null while it is valid.")


class ApiKeyCreated(BaseModel):
    """A new API key, with its secret: the only reply that shows it."""

    model_config = ConfigDict(json_schema_extra=_examples(
        {"id": 3, "name": "stage camera 1", "scopes": ["read", "track"],
         "key": "ft_a68bcba0ef37_c2Ks_9LeRpjTXOcxAa-iRYRlURFBpOg_h4RQ8FEgg1M"}))

    id: int = Field(description="The key's id.")
    name: str = Field(description="Its name.")
    scopes: list[str] = Field(description="What it may do: read, track, admin.")
    key: str = Field(description="The secret: shown once, only its hash is stored.")
