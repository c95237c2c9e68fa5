"""Service settings, read from the environment with the prefix ``FIDOTRACK_``."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, computed_field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError, NoSuchModuleError


#: The most files a survey upload's form is parsed with; `Settings.max_survey_images` may
#: not exceed it. Past it the form is refused before the service sees it (HTTP 400).
MAX_SURVEY_FILES = 20000

#: URL schemes taken to mean PostgreSQL through psycopg 3 (the `postgres` extra's driver):
#: SQLAlchemy reads a bare ``postgresql://`` as psycopg2, which the project does not
#: install, and refuses ``postgres://``.
POSTGRES_SCHEMES = ("postgresql://", "postgres://")
POSTGRES_PSYCOPG = "postgresql+psycopg://"


class Settings(BaseSettings):
    """Everything a deployment can set; ``uvicorn app.main:app`` reads these."""

    # Errors do not echo the values: a database URL may carry a password.
    model_config = SettingsConfigDict(env_prefix="FIDOTRACK_", env_file=None, extra="ignore",
                                      hide_input_in_errors=True)

    data_dir: Path = Field(Path("data"), description="Directory for the SQLite file, uploads and locks.")
    database_url: str | None = Field(None, description=(
        "A SQLAlchemy URL of the database; default: a SQLite file under data_dir. PostgreSQL: "
        "`postgresql://user:password@host:5432/name` (psycopg 3, the `postgres` extra; the same as "
        "`postgresql+psycopg://`)."))
    host: str = Field("127.0.0.1", description="Address where `fidotrack serve` listens.")
    port: int = Field(8000, ge=1, le=65535, description="Port where `fidotrack serve` listens.")
    tls_certfile: Path | None = Field(None, description=(
        "PEM certificate (chain) for `fidotrack serve` to serve https and wss itself; with `tls_keyfile`. "
        "Browsers give a page the camera only over https or on localhost."))
    tls_keyfile: Path | None = Field(None, description="PEM private key of `tls_certfile`.")
    sqlite_busy_timeout_ms: int = Field(
        5000, ge=0, description="SQLite busy timeout, ms: how long a write waits for another writer's lock.")

    api_keys: bool = Field(False, description="Require API keys (create them with `fidotrack keys create`).")
    log_format: str = Field("json", pattern="^(json|text)$", description="Log lines as JSON objects or text.")
    log_level: str = Field("INFO", pattern="^(DEBUG|INFO|WARNING|ERROR)$",
                           description="Least severe level of the structured logs on stderr.")

    # Limits on what clients send.
    max_upload_bytes: int = Field(512 * 1024 * 1024, ge=1024, description="Largest survey upload.")
    max_image_bytes: int = Field(20 * 1024 * 1024, ge=1024, description=(
        "Largest image: a /detect or /locate body, a training image, a decoded frame."))
    max_json_bytes: int = Field(1024 * 1024, ge=1024, description=(
        "Largest JSON body (a map of every card of the largest family is about 0.1 MiB) and of any other "
        "request that is not an upload or an image."))
    max_image_pixels: int = Field(40_000_000, ge=64 * 64, description="Largest width*height decoded.")
    max_frame_bytes: int = Field(4 * 1024 * 1024, ge=1024, description="Largest /track frame (one binary WebSocket message).")
    max_training_images: int = Field(200, ge=1, description="Most images in one training upload.")
    max_video_frames: int = Field(20_000, ge=1, description="Longest survey video, in frames.")
    max_video_pixels: int = Field(3840 * 2160, ge=64 * 64, description="Largest survey video frame (width*height).")
    max_survey_images: int = Field(2000, ge=1, le=MAX_SURVEY_FILES, description=(
        f"Most images in one survey upload (at most {MAX_SURVEY_FILES}, the most files the upload's form is read "
        "with)."))
    survey_frames: int = Field(1000, ge=2, le=20_000, description="Frames a survey uses by default (evenly spaced).")
    max_track_fps: float = Field(120.0, gt=0, description="Frames per second one /track client may send.")
    freed_connection_receivers: bool = Field(True, description=(
        "Whether a /track connection may send FreeD packets to a host and port of its own choosing (config "
        "`freed`); false: only to its environment's FreeD output."))
    max_track_connections: int = Field(64, ge=1, description=(
        "Open /track connections at once, across every server process sharing the database."))
    track_idle_timeout_s: float = Field(30.0, gt=0, le=86400, description=(
        "A /track connection that sends no message for this long is closed (error `idle`, close code 1001), "
        "so that idle clients cannot hold every connection slot."))
    max_queued_jobs: int = Field(20, ge=1, description=(
        "Jobs queued or running at once, across every server process sharing the database; more get 429."))
    track_threads: int = Field(2, ge=1, le=64, description="Threads processing tracking frames.")
    image_workers: int = Field(1, ge=1, le=64, description=(
        "Processes for /detect and /locate images, apart from the web process and its /track frames: those "
        "requests queue for them, so that a burst of them cannot take the cores /track streams need."))
    image_workers_nice: int = Field(19, ge=0, le=19, description=(
        "How much lower the OS priority of the image workers is than the web process's (a nice increment; "
        "0: the same)."))
    max_image_requests: int = Field(32, ge=1, description=(
        "/detect and /locate requests being read, queued or processed at once; more get 503."))
    image_memory_bytes: int = Field(1024 * 1024 * 1024, ge=64 * 1024 * 1024, description=(
        "Memory the client images being decoded and detected may hold at once, all routes together (each "
        "image's cost is read from its header): an image that alone needs more is refused (413), others "
        "wait for room."))
    compute_threads: int = Field(1, ge=1, le=64, description=(
        "Threads one frame's detection and pose may use inside OpenCV and BLAS. Frames of "
        "different clients already run in parallel (track_threads); 1 keeps idle BLAS "
        "threads from spinning on the cores the other frames need."))
    max_concurrent_jobs: int = Field(1, ge=1, le=16, description=(
        "Jobs running at once in the embedded job cluster (its workers); with `job_scheduler`, each "
        "`fidotrack worker` runs one job at a time and the number of workers sets it."))
    job_scheduler: str | None = Field(None, pattern=r"^(tcp|tls)://[^\s]+:[0-9]{1,5}$", description=(
        "Address of the job engine's scheduler (Dask distributed), e.g. `tcp://scheduler:8786`, whose "
        "`fidotrack worker`s on any machine run surveys and training; default: a local cluster started "
        "by `fidotrack serve`, with `max_concurrent_jobs` workers."))
    job_heartbeat_s: float = Field(5.0, gt=0, le=300, description=(
        "How often a running job's worker says on the job's row that it is alive."))
    job_lease_s: float = Field(30.0, gt=0, le=3600, description=(
        "A running job whose worker has said nothing for this long is failed (\"worker lost\"), by any "
        "web process; more than `job_heartbeat_s` with room for a busy database."))
    job_attempts: int = Field(2, ge=1, le=10, description=(
        "Runs a job gets when the worker running it dies (its process killed, its machine gone): the "
        "engine runs it again on another worker, at most this many times in all, then it fails."))
    track_connection_lease_s: float = Field(30.0, ge=2, le=3600, description=(
        "An open /track connection is renewed in the database this often / 3; one a dead server process "
        "left behind stops counting against `max_track_connections` after this long."))
    map_poll_s: float = Field(2.0, gt=0, le=3600, description=(
        "How often an open /track connection checks whether its environment's map or classifier changed "
        "(a survey, an alignment, on any server process) and switches to the new one."))

    # Job engine sockets and TLS.

    # FreeD receivers a /track connection may name.

    # Origins allowed to open /track and send state-changing requests.

    # Slow clients: header and body timeouts, connections per address.

    # Per-key and per-address limits on /track connections and request rate.

    # Uploads in flight.

    @field_validator("database_url")
    @classmethod
    def _database_url(cls, url: str | None) -> str | None:
        """The URL with PostgreSQL's plain schemes read as psycopg 3; refused at start,
        saying why, when it is not a URL SQLAlchemy knows or its driver is not installed
        (rather than at the first connection, deep in the start-up)."""
        if not url:
            return None
        for scheme in POSTGRES_SCHEMES:
            if url.startswith(scheme):
                url = POSTGRES_PSYCOPG + url[len(scheme):]
        try:
            parsed = make_url(url)
            dialect = parsed.get_dialect()
        except (ArgumentError, NoSuchModuleError, ValueError) as exc:
            raise ValueError(f"not a database URL that SQLAlchemy knows: {exc}") from None
        try:
            dialect.import_dbapi()
        except ImportError as exc:
            hint = " (pip install 'fidotrack[postgres]')" if url.startswith(POSTGRES_PSYCOPG) else ""
            raise ValueError(f"the driver of {parsed.drivername} URLs is not installed: {exc}{hint}") from None
        return url

    @computed_field  # type: ignore[prop-decorator]
    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'fidotrack.db').as_posix()}"
