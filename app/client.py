"""A Python client of the fidotrack service: typed replies, errors with the service's
message, a survey that reports its progress, and `Client.track`, an iterator of poses
over frames streamed to ``/track`` in lock-step.

    from app.client import Client

    with Client("http://localhost:8000") as fidotrack:
        environment = fidotrack.create_environment("studio", marker_size_m=0.2)
        job = fidotrack.survey(environment.id, "room.mp4", progress=print)   # job.result: a SurveyResult
        for reply in fidotrack.track(environment.id, frames):  # JPEG bytes or numpy images
            print(reply.seq, reply.pose.position if reply.pose else reply.pose_error)

The replies are the service's own models (`app.schemas`): what the API documents is what
the client returns.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, BinaryIO, Self

import httpx
import numpy as np

from app.schemas import (
    AlignmentRequest,
    AlignmentResult,
    DetectResponse,
    EnvironmentOut,
    FreeDOutput,
    JobOut,
    JobStatus,
    LocateResponse,
    MapDocument,
    MapVersionOut,
    TrackConfig,
    TrackFrame,
    TrackHello,
)

__all__ = ["ApiError", "Client", "JobFailed", "MapChanged", "TrackRefused", "encode_frame"]

#: Job states after which a job never changes.
FINISHED = frozenset({JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELLED})
#: /track errors that are notices about the stream: the frame's reply still follows.
NOTICES = frozenset({"rate_limited", "freed"})


class ApiError(Exception):
    """The service refused a request: its HTTP status and its message."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(f"{status}: {detail}")
        self.status = status
        self.detail = detail


class MapChanged(ApiError):
    """A map write refused (412) because the map changed since this client read it: read
    it again (`Client.get_map`) and redo the change, or write with ``overwrite=True``."""

    def __init__(self, environment_id: int, detail: str) -> None:
        super().__init__(412, f"the map of environment {environment_id} changed since this client read it, so "
                              f"nothing was written ({detail}); get_map() it again and redo the change on it, or "
                              "pass overwrite=True to replace whatever it is now")
        self.environment_id = environment_id


class JobFailed(Exception):
    """A job ended without success (failed or cancelled)."""

    def __init__(self, job: JobOut) -> None:
        super().__init__(f"job {job.id} {job.status}: {job.error or job.message or job.stage}")
        self.job = job


class TrackRefused(Exception):
    """``/track`` refused the connection or closed it: the code and message it gave."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


def encode_frame(image: bytes | np.ndarray, quality: int = 90) -> bytes:
    """A frame as the service takes it: JPEG bytes as given, or a numpy image encoded.

    Parameters
    ----------
    image : bytes or (H, W) or (H, W, 3) uint8 ndarray
        An encoded image (JPEG or PNG), or pixels (grey, or BGR as OpenCV reads them).
    quality : int
        JPEG quality for pixels.

    Returns
    -------
    bytes
    """
    if isinstance(image, bytes | bytearray | memoryview):
        return bytes(image)
    import cv2

    ok, data = cv2.imencode(".jpg", np.asarray(image), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError(f"cannot encode an image of shape {np.shape(image)} as JPEG")
    return data.tobytes()


class Client:
    """The service at `base_url`, with an API key when it requires one.

    Parameters
    ----------
    base_url : str
        E.g. ``http://localhost:8000``.
    api_key : str, optional
        Sent as ``X-API-Key`` (and as ``api_key`` on ``/track``).
    timeout : float
        Seconds for each HTTP request.
    """

    def __init__(self, base_url: str = "http://127.0.0.1:8000", api_key: str | None = None,
                 timeout: float = 60.0) -> None:
        self.base_url = base_url.rstrip("/")
        self.api_key = api_key
        headers = {"X-API-Key": api_key} if api_key else {}
        self.http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout)
        # The ETag of each environment's map as this client last read or wrote it: its map
        # writes are conditional on it (If-Match).
        self._map_etags: dict[int, str] = {}

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the HTTP connections."""
        self.http.close()

    # -- plumbing ------------------------------------------------------------------------

    def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            response = self.http.request(method, path, **kwargs)
        except httpx.TransportError as exc:
            raise ApiError(0, f"cannot reach the service at {self.base_url}: {exc}") from exc
        if response.status_code >= 400:
            try:
                detail = response.json().get("detail", response.text)
            except ValueError:
                detail = response.text or response.reason_phrase
            raise ApiError(response.status_code, detail if isinstance(detail, str) else json.dumps(detail))
        return response

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        return self._request(method, path, **kwargs).json()

    # -- service -------------------------------------------------------------------------

    def ready(self) -> bool:
        """Whether the service answers ``/readyz`` with 200."""
        try:
            return self.http.get("/readyz").status_code == 200
        except httpx.TransportError:
            return False

    def wait_ready(self, timeout_s: float = 120.0) -> None:
        """Wait until the service is ready (its kernels compiled, its database at head)."""
        deadline = time.monotonic() + timeout_s
        while not self.ready():
            if time.monotonic() > deadline:
                raise ApiError(0, f"the service at {self.base_url} was not ready within {timeout_s:.0f} s")
            time.sleep(0.2)

    # -- environments and maps -------------------------------------------------------------

    def environments(self) -> list[EnvironmentOut]:
        """Every environment."""
        return [EnvironmentOut.model_validate(e) for e in self._json("GET", "/environments")]

    def environment(self, environment_id: int) -> EnvironmentOut:
        """One environment."""
        return EnvironmentOut.model_validate(self._json("GET", f"/environments/{environment_id}"))

    def create_environment(self, name: str, marker_size_m: float, classifier_id: int | None = None,
                           marker_family: str = "fido3x3") -> EnvironmentOut:
        """A new environment for cards of side `marker_size_m` (metres, as printed)."""
        body = {"name": name, "marker_size_m": marker_size_m, "classifier_id": classifier_id,
                "marker_family": marker_family}
        return EnvironmentOut.model_validate(self._json("POST", "/environments", json=body))

    def delete_environment(self, environment_id: int) -> None:
        """Delete an environment and its map."""
        self._request("DELETE", f"/environments/{environment_id}")
        self._map_etags.pop(environment_id, None)

    def get_map(self, environment_id: int) -> MapDocument:
        """The environment's map; the client keeps its revision (`map_etag`) for the writes
        that follow."""
        return MapDocument.model_validate(self._map_request("GET", environment_id, "/map").json())

    def map_etag(self, environment_id: int) -> str | None:
        """The ETag of the environment's map as this client last read or wrote it (e.g.
        ``'"7"'``), or None."""
        return self._map_etags.get(environment_id)

    def _map_request(self, method: str, environment_id: int, path: str, *, if_match: str | None = None,
                     overwrite: bool = False, **kwargs: Any) -> httpx.Response:
        """A request that reads or writes the environment's map. A write sends ``If-Match``:
        `if_match` when given, else the ETag this client knows (none with `overwrite`), and
        raises MapChanged when the map has changed since. The reply's ETag is kept."""
        if method != "GET":
            condition = if_match or (None if overwrite else self._map_etags.get(environment_id))
            if condition is not None:
                kwargs["headers"] = {**kwargs.get("headers", {}), "If-Match": condition}
        try:
            response = self._request(method, f"/environments/{environment_id}{path}", **kwargs)
        except ApiError as error:
            if error.status == 412:
                raise MapChanged(environment_id, error.detail) from None
            raise
        if "ETag" in response.headers:
            self._map_etags[environment_id] = response.headers["ETag"]
        return response

    def put_map(self, environment_id: int, document: MapDocument | dict[str, Any], *, if_match: str | None = None,
                overwrite: bool = False) -> MapDocument:
        """Store a map (an import, or one surveyed elsewhere) as the environment's map.

        Only over the map this client last read or wrote, if it did (``If-Match``; else
        `MapChanged`), or over the map at `if_match` (an ETag); `overwrite` replaces
        whatever map there is."""
        body = document.model_dump(mode="json") if isinstance(document, MapDocument) else document
        return MapDocument.model_validate(self._map_request("PUT", environment_id, "/map", json=body,
                                                            if_match=if_match, overwrite=overwrite).json())

    def map_versions(self, environment_id: int) -> list[MapVersionOut]:
        """The maps earlier changes replaced, the newest first."""
        return [MapVersionOut.model_validate(v) for v in self._json("GET", f"/environments/{environment_id}/map/versions")]

    def restore_map(self, environment_id: int, version: int | None = None, *, if_match: str | None = None,
                    overwrite: bool = False) -> MapDocument:
        """Make an earlier map current again: the newest, or `version` (conditional as
        `put_map`)."""
        body = {"version": version} if version is not None else {}
        return MapDocument.model_validate(self._map_request("POST", environment_id, "/map/restore", json=body,
                                                            if_match=if_match, overwrite=overwrite).json())

    def align(self, environment_id: int, request: AlignmentRequest | dict[str, Any], *, if_match: str | None = None,
              overwrite: bool = False) -> AlignmentResult:
        """Move the map into world coordinates (known points, or an origin card); conditional
        as `put_map`."""
        body = request.model_dump(mode="json", exclude_none=True) if isinstance(request, AlignmentRequest) else request
        return AlignmentResult.model_validate(self._map_request("POST", environment_id, "/alignment", json=body,
                                                                if_match=if_match, overwrite=overwrite).json())

    def freed_output(self, environment_id: int) -> FreeDOutput | None:
        """The environment's FreeD output, or None without one."""
        try:
            return FreeDOutput.model_validate(self._json("GET", f"/environments/{environment_id}/freed"))
        except ApiError as error:
            if error.status == 404:
                self.environment(environment_id)  # no such environment: its 404 instead
                return None
            raise

    def set_freed_output(self, environment_id: int, output: FreeDOutput | dict[str, Any]) -> FreeDOutput:
        """Send the environment's poses as FreeD packets to a receiver (docs/freed.md)."""
        body = output.model_dump(mode="json") if isinstance(output, FreeDOutput) else output
        return FreeDOutput.model_validate(self._json("PUT", f"/environments/{environment_id}/freed", json=body))

    def remove_freed_output(self, environment_id: int) -> None:
        """Stop sending the environment's poses as FreeD packets."""
        self._request("DELETE", f"/environments/{environment_id}/freed")

    def sheet(self, ids: str, size_mm: float, family: str = "fido3x3") -> bytes:
        """An A4 PDF of the cards `ids` (e.g. ``"0-11"``) at `size_mm`."""
        return self._request("GET", "/markers/sheet.pdf",
                             params={"ids": ids, "size_mm": size_mm, "family": family}).content

    # -- one image ---------------------------------------------------------------------

    def detect(self, image: bytes | np.ndarray, candidates: bool = False,
               classifier_id: int | None = None) -> DetectResponse:
        """The targets in one image (JPEG/PNG bytes, or pixels)."""
        params: dict[str, Any] = {"candidates": candidates}
        if classifier_id is not None:
            params["classifier_id"] = classifier_id
        return DetectResponse.model_validate(self._json("POST", "/detect", content=encode_frame(image),
                                                        params=params, headers={"Content-Type": "image/jpeg"}))

    def locate(self, environment_id: int, image: bytes | np.ndarray) -> LocateResponse:
        """The targets in one image and the camera's pose in the environment's map."""
        return LocateResponse.model_validate(self._json(
            "POST", f"/environments/{environment_id}/locate", content=encode_frame(image),
            headers={"Content-Type": "image/jpeg"}))

    # -- jobs and surveys --------------------------------------------------------------

    def job(self, job_id: str) -> JobOut:
        """A job's state."""
        return JobOut.model_validate(self._json("GET", f"/jobs/{job_id}"))

    def cancel(self, job_id: str) -> JobOut:
        """Ask a job to stop."""
        return JobOut.model_validate(self._json("DELETE", f"/jobs/{job_id}"))

    def wait(self, job_id: str, progress: Callable[[JobOut], None] | None = None, poll_s: float = 0.5,
             timeout_s: float | None = None) -> JobOut:
        """Poll a job until it ends; `progress` gets each state seen. Returns the final state
        (whatever its status)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            job = self.job(job_id)
            if progress is not None:
                progress(job)
            if job.status in FINISHED:
                return job
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job.status} after {timeout_s} s")
            time.sleep(poll_s)

    def start_survey(self, environment_id: int, video: str | Path | BinaryIO, *, max_frames: int | None = None,
                     marker_size_m: float | None = None, feature_tracks: bool = True,
                     readout_ms: float | None = None) -> JobOut:
        """Upload a video of the room and start its survey (a job); ``feature_tracks=False``:
        the cards alone, without the walls' own texture; ``readout_ms``: the camera's
        rolling shutter readout, first row to last (a phone's: 10-30 ms)."""
        form: dict[str, str] = {"feature_tracks": "true" if feature_tracks else "false"}
        if readout_ms is not None:
            form["readout_ms"] = str(readout_ms)
        if max_frames is not None:
            form["max_frames"] = str(max_frames)
        if marker_size_m is not None:
            form["marker_size_m"] = str(marker_size_m)
        if isinstance(video, str | Path):
            with open(video, "rb") as handle:
                files = {"video": (Path(video).name, handle, "application/octet-stream")}
                return JobOut.model_validate(self._json("POST", f"/environments/{environment_id}/survey",
                                                        files=files, data=form))
        files = {"video": ("video", video, "application/octet-stream")}
        return JobOut.model_validate(self._json("POST", f"/environments/{environment_id}/survey",
                                                files=files, data=form))

    def survey(self, environment_id: int, video: str | Path | BinaryIO,
               progress: Callable[[JobOut], None] | None = None, **options: Any) -> JobOut:
        """Survey the environment from a video and wait for the map: the finished job.

        Raises
        ------
        JobFailed
            When the survey failed or was cancelled (the environment keeps its old map).
        """
        job = self.wait(self.start_survey(environment_id, video, **options).id, progress)
        if job.status != JobStatus.SUCCEEDED:
            raise JobFailed(job)
        # This client replaced the map it knew itself: its writes no longer depend on that one.
        self._map_etags.pop(environment_id, None)
        return job

    # -- tracking ----------------------------------------------------------------------

    def track_url(self, environment_id: int) -> str:
        """The ``/track`` WebSocket address of an environment."""
        url = self.base_url.replace("https://", "wss://", 1).replace("http://", "ws://", 1)
        query = f"?environment_id={environment_id}"
        return url + "/track" + query

    def track(self, environment_id: int, frames: Iterable[bytes | np.ndarray], config: TrackConfig | None = None,
              quality: int = 90, on_hello: Callable[[TrackHello], None] | None = None) -> Iterator[TrackFrame]:
        """Stream `frames` to ``/track`` in lock-step (each frame leaves when the previous
        reply is in, so nothing queues up) and yield the reply to each, in order.

        Frames the service refuses (``bad_frame``, ``frame_too_large``) are skipped with no
        reply; a refused connection, or a refused `config`, raises `TrackRefused`.

        `on_hello` gets the connection's hello, and each later one: the service sends one
        (``reason`` ``map_changed`` or ``classifier_changed``) when the environment's map
        or classifier changes while the connection is open; the replies after it are posed
        against the new map. The environment deleted meanwhile raises `TrackRefused`.
        """
        from websockets.exceptions import ConnectionClosed
        from websockets.sync.client import connect

        def receive(ws: Any) -> dict[str, Any]:
            """The next message that is not a hello (those go to `on_hello`)."""
            while True:
                try:
                    message = json.loads(ws.recv(timeout=60))
                except ConnectionClosed as closed:
                    reason = closed.rcvd.reason if closed.rcvd is not None else "the connection closed"
                    raise TrackRefused("closed", reason) from closed
                if message.get("type") != "hello":
                    return message
                hello = TrackHello.model_validate(message)
                if on_hello is not None:
                    on_hello(hello)

        headers = {"X-API-Key": self.api_key} if self.api_key else None
        with connect(self.track_url(environment_id), additional_headers=headers, max_size=None,
                     open_timeout=30) as ws:
            hello = json.loads(ws.recv(timeout=30))
            if hello.get("type") != "hello":
                raise TrackRefused(hello.get("code", "refused"), hello.get("message", str(hello)))
            first = TrackHello.model_validate(hello)
            if on_hello is not None:
                on_hello(first)
            if config is not None:
                ws.send(config.model_dump_json())
                echo = receive(ws)  # the config echoed, or why it is refused
                if echo.get("type") == "error":
                    raise TrackRefused(echo.get("code", "error"), echo.get("message", ""))
            for frame in frames:
                try:
                    ws.send(encode_frame(frame, quality))
                except ConnectionClosed:  # closed after the last reply (its reason follows)
                    pass
                message = receive(ws)
                while message.get("type") == "error" and message.get("code") in NOTICES:
                    message = receive(ws)  # the frame's reply is still to come
                if message.get("type") == "frame":
                    yield TrackFrame.model_validate(message)
                elif message.get("type") == "error" and message.get("seq") is None:
                    raise TrackRefused(message.get("code", "error"), message.get("message", ""))
