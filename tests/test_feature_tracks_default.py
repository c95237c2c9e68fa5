"""Feature tracks are the survey's default everywhere a survey is started: the REST form,
the client, the command line and the web app; each turns them off when asked."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import httpx

from app.cli import build_parser
from app.client import Client
from app.routers.surveys import SurveyForm
from app.services.surveys import SurveyParams

from tests.conftest import NEEDS_CHROMIUM, running_server

_JOB = {"id": "a" * 32, "kind": "survey", "status": "queued", "progress": 0.0, "stage": "queued", "message": "",
        "environment_id": 1, "created_at": "2026-11-20T09:20:04Z", "started_at": None, "finished_at": None,
        "result": None, "error": None}


def test_the_rest_form_and_the_job_track_features_unless_told_not_to() -> None:
    assert SurveyForm().feature_tracks is True
    assert SurveyForm.model_validate({"feature_tracks": "false"}).feature_tracks is False
    assert SurveyParams.model_fields["feature_tracks"].default is True


def _sent_forms(tmp_path: Path, **options: Any) -> dict[str, str]:
    """The form fields the client sends to start a survey with `options`."""
    video = tmp_path / "room.mp4"
    video.write_bytes(b"\x00" * 64)
    sent: list[bytes] = []

    def reply(request: httpx.Request) -> httpx.Response:
        sent.append(request.read())
        return httpx.Response(202, json=_JOB)

    with Client("http://fidotrack.test") as client:
        client.http = httpx.Client(base_url=client.base_url, transport=httpx.MockTransport(reply))
        client.start_survey(1, video, **options)
    body = sent[0].decode("latin-1")
    fields = {}
    for part in body.split("Content-Disposition: form-data; name=\"")[1:]:
        name, rest = part.split("\"", 1)
        if name != "video":
            fields[name] = rest.split("\r\n\r\n", 1)[1].split("\r\n", 1)[0]
    return fields


def test_the_client_tracks_features_unless_told_not_to(tmp_path: Path) -> None:
    assert _sent_forms(tmp_path)["feature_tracks"] == "true"
    assert _sent_forms(tmp_path, feature_tracks=False)["feature_tracks"] == "false"


def test_the_survey_command_tracks_features_unless_told_not_to() -> None:
    parser = build_parser()
    assert parser.parse_args(["survey", "room.mp4", "-e", "1"]).feature_tracks is True
    assert parser.parse_args(["survey", "room.mp4", "-e", "1", "--no-feature-tracks"]).feature_tracks is False
    assert parser.parse_args(["survey", "room.mp4", "-e", "1", "--feature-tracks"]).feature_tracks is True


@NEEDS_CHROMIUM
def test_the_web_apps_survey_form_tracks_features_unless_unticked(tmp_path: Path, browser: Any) -> None:
    video = tmp_path / "room.mp4"
    video.write_bytes(b"\x00" * 64)
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        env = httpx.post(f"{server.url}/environments", json={"name": "room", "marker_size_m": 0.2}).json()["id"]
        page = browser.new_context().new_page()
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        bodies: list[str] = []

        def held(route: Any) -> None:  # the form as sent; no survey is run
            bodies.append((route.request.post_data_buffer or b"").decode("latin-1"))
            route.fulfill(status=202, content_type="application/json", body=httpx.Response(202, json=_JOB).text)

        page.route("**/environments/*/survey", held)
        page.route("**/jobs/*", lambda route: route.fulfill(status=200, content_type="application/json", body=(
            httpx.Response(200, json={**_JOB, "status": "cancelled", "stage": "cancelled"}).text)))
        page.goto(f"{server.url}/app/#/environments/{env}/survey")
        page.wait_for_selector("#survey-features")
        assert page.is_checked("#survey-features")
        page.set_input_files("input[name=video]", str(video))
        for untick, sent in ((False, "true"), (True, "false")):
            if untick:
                page.uncheck("#survey-features")
            page.click("button:text-is('Upload and survey'):enabled", timeout=30_000)
            for _ in range(300):
                if len(bodies) == (2 if untick else 1):
                    break
                page.wait_for_timeout(100)
            field = bodies[-1].split('name="feature_tracks"', 1)[1].split("\r\n\r\n", 1)[1].split("\r\n", 1)[0]
            assert field == sent
            page.wait_for_selector("#survey-result >> text=cancelled", timeout=30_000)
    assert errors == []
