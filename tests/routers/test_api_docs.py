"""The API explains itself: every route of the OpenAPI document has a summary in a
person's words and a description, every field of every schema says what it is, every
JSON body carries an example that the service itself accepts, a job's result is typed
by its kind, and the /track messages are schemas of the document too."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient
from pydantic import BaseModel

from app import schemas
from app.core.survey.advice import WarningKind
from app.main import create_app
from app.routers import classifiers, detect, environments, health, jobs, keys, markers, surveys, track
from app.schemas import JobOut, SurveyResult, TrainingResult, complete_openapi, track_message_schemas
from app.services.jobs import JobKind

#: Form bodies that FastAPI makes from a route's form fields: their fields carry
#: descriptions, their examples are the routes' own documentation.
FORM_BODY_PREFIX = "Body_"


@pytest.fixture(scope="module")
def openapi() -> dict[str, Any]:
    """The application's document, completed as the application completes it."""
    return complete_openapi(json.loads(json.dumps(create_app().openapi())))


def _operations(openapi: dict[str, Any]) -> Iterator[tuple[str, str, dict[str, Any]]]:
    for path, operations in openapi["paths"].items():
        for method, operation in operations.items():
            yield path, method, operation


def _generated_summary(name: str) -> str:
    # What FastAPI makes of a route function's name when it is given no summary.
    return name.replace("_", " ").title()


def test_every_route_has_a_summary_in_words_and_a_description(openapi: dict[str, Any]) -> None:
    routers = (classifiers, detect, environments, health, jobs, keys, markers, surveys, track)
    names = {(route.path, method.lower()): route.name for module in routers for route in module.router.routes
             if isinstance(route, APIRoute) for method in route.methods}
    lacking = []
    for path, method, operation in _operations(openapi):
        assert (path, method) in names, f"{method.upper()} {path} is not in a router this test knows"
        summary = operation.get("summary", "")
        if not summary or summary == _generated_summary(names[(path, method)]):
            lacking.append(f"{method.upper()} {path}: summary {summary!r}")
        if not operation.get("description", "").strip():
            lacking.append(f"{method.upper()} {path}: no description")
    assert not lacking, "\n".join(lacking)


def test_every_property_of_every_schema_says_what_it_is(openapi: dict[str, Any]) -> None:
    components = openapi["components"]["schemas"]
    blank = [f"{name}.{field}" for name, schema in components.items()
             for field, prop in schema.get("properties", {}).items() if not prop.get("description", "").strip()]
    assert not blank, f"properties without a description: {blank}"
    # The service's own 422 body, not FastAPI's default (which does not match what it sends).
    assert "HTTPValidationError" not in components


def _body_refs(openapi: dict[str, Any]) -> set[str]:
    """The component names of every JSON request and reply body (lists by their items)."""
    refs = set()
    for _path, _method, operation in _operations(openapi):
        contents = [operation.get("requestBody", {}).get("content", {})]
        contents += [reply.get("content", {}) for reply in operation["responses"].values()]
        for content in contents:
            schema = content.get("application/json", {}).get("schema", {})
            schema = schema.get("items", schema)
            if "$ref" in schema:
                refs.add(schema["$ref"].rsplit("/", 1)[-1])
    return refs


def test_every_json_body_has_an_example_the_service_accepts(openapi: dict[str, Any]) -> None:
    components = openapi["components"]["schemas"]
    bodies = _body_refs(openapi)
    assert {"EnvironmentCreate", "JobOut", "DetectResponse", "MapDocument", "ValidationProblem"} <= bodies
    for name in sorted(bodies):
        if name.startswith(FORM_BODY_PREFIX):
            continue
        examples = components[name].get("examples")
        assert examples, f"{name} has no example"
        model = getattr(schemas, name)
        for example in examples:
            # As a client would send it or read it: through JSON, its null fields included.
            model.model_validate_json(json.dumps(example))
    assert components["JobOut"]["examples"][0]["error"] is None


def test_track_messages_are_schemas_of_the_document_with_their_examples(openapi: dict[str, Any]) -> None:
    components = openapi["components"]["schemas"]
    for model in schemas.TRACK_MESSAGES:
        schema = components[model.__name__]
        assert schema["description"] and schema["examples"], model.__name__
        for example in schema["examples"]:
            model.model_validate_json(json.dumps(example))
    # The parts they share with the HTTP replies are the same schemas.
    plain = create_app().openapi()["components"]["schemas"]
    messages = track_message_schemas()
    def without_null_defaults(schema: Any) -> Any:  # FastAPI's encoder drops them from the HTTP document
        if isinstance(schema, dict):
            return {k: without_null_defaults(v) for k, v in schema.items() if not (k == "default" and v is None)}
        return [without_null_defaults(v) for v in schema] if isinstance(schema, list) else schema

    for shared in ("CameraModel", "DetectedTargetOut", "PoseOut"):
        assert without_null_defaults({**messages[shared], "examples": 0}) == {**plain[shared], "examples": 0}
    # Every reference of the completed document resolves; completing it again changes nothing.
    text = json.dumps(openapi)
    for ref in {part.split('"')[0] for part in text.split('"$ref": "#/components/schemas/')[1:]}:
        assert ref in components, ref
    assert complete_openapi(json.loads(text)) == openapi


def test_a_jobs_result_is_typed_by_its_kind_in_the_schema(openapi: dict[str, Any]) -> None:
    result = openapi["components"]["schemas"]["JobOut"]["properties"]["result"]
    refs = {option.get("$ref", "").rsplit("/", 1)[-1] for option in result["anyOf"]}
    assert refs == {"SurveyResult", "TrainingResult", ""}  # "" is null
    assert {"null"} == {option["type"] for option in result["anyOf"] if "type" in option}
    assert set(schemas.RESULT_MODELS) == {kind.value for kind in JobKind}
    assert {kind.value for kind in schemas.CardWarningKind} == {kind.value for kind in WarningKind}


def _job(kind: str, result: dict[str, Any] | None) -> dict[str, Any]:
    return {"id": "a" * 32, "kind": kind, "status": "succeeded", "progress": 1.0, "stage": "done", "message": "done",
            "environment_id": 1, "created_at": "2026-11-20T09:20:04Z", "started_at": "2026-11-20T09:20:05Z",
            "finished_at": "2026-11-20T09:21:47Z", "result": result, "error": None}


def test_results_stored_by_earlier_versions_still_read() -> None:
    # A survey's result before the lens's uncertainty, the typed card warnings and
    # feature tracks were reported.
    oldest = {"n_frames": 2, "n_registered": 2, "n_targets": 1, "rms_px": 0.4, "focal_px": 820.0,
              "principal_point": [320.0, 240.0], "dist": [-0.1, 0.0, 0.0, 0.0, 0.0], "warnings": [],
              "timing_s": {"bundle": 1.0}, "frames_used": 2, "detections": 2,
              "trajectory": [{"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 2], "position": [0, 0, -2]}, None]}
    job = JobOut.model_validate(_job("survey", oldest))
    assert isinstance(job.result, SurveyResult)
    assert job.result.card_warnings == [] and job.result.intrinsics_std is None and job.result.feature_tracks is False
    served = json.loads(job.model_dump_json())["result"]
    assert {k: served[k] for k in oldest} == oldest
    trained = JobOut.model_validate(_job("train_classifier", {"images": 2, "stats": {"site_images": 2},
                                                              "classifier_id": 4}))
    assert isinstance(trained.result, TrainingResult) and trained.result.classifier_id == 4
    # A kind without a model of its own keeps its result as it is.
    assert JobOut.model_validate(_job("count", {"counted": 20})).result == {"counted": 20}


def test_a_stored_survey_result_is_served_whole_and_typed(client: TestClient) -> None:
    from app.models import Job
    from app.services.jobs import store

    class _Params(BaseModel):
        upload_dir: str = "none"

    example = schemas._EXAMPLE_SURVEY_RESULT
    with client.app.state.sessionmaker() as session:
        row = store.create(session, JobKind.SURVEY.value, _Params())
        stored = session.get(Job, row.id)
        assert stored is not None
        stored.status, stored.result = "succeeded", example
        session.commit()
        job_id = row.id
    body = client.get(f"/jobs/{job_id}").json()
    assert body["result"] == json.loads(json.dumps(example))
    assert body["result"]["card_warnings"][0]["kind"] == "few views"
