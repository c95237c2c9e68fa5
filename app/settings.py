"""Service settings, read from the environment with the prefix ``FIDOTRACK_``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated
from urllib.parse import urlsplit

from pydantic import Field, IPvAnyNetwork, computed_field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict
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

#: The port a browser leaves out of an origin, by scheme.
DEFAULT_PORTS = {"http": 80, "https": 443}


def normalize_origin(origin: str) -> str:
    """`origin` (``scheme://host[:port]``, http or https) as a browser's ``Origin`` header
    writes it: lower case, without the scheme's default port. ValueError if it is not one."""
    try:
        parts = urlsplit(origin.strip())
        port = parts.port
    except ValueError:
        raise ValueError(f"not an origin (scheme://host[:port]): {origin!r}") from None
    scheme = parts.scheme.lower()
    if (scheme not in DEFAULT_PORTS or not parts.hostname or parts.username is not None
            or parts.password is not None or parts.path not in ("", "/") or parts.query or parts.fragment):
        raise ValueError(f"not an origin (http or https://host[:port], nothing after): {origin!r}")
    host = f"[{parts.hostname}]" if ":" in parts.hostname else parts.hostname
    return f"{scheme}://{host}" + (f":{port}" if port is not None and port != DEFAULT_PORTS[scheme] else "")


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
    freed_connection_receivers: bool = Field(False, description=(
        "Whether a /track connection may send FreeD packets to a host and port of its own choosing (config "
        "`freed`), inside `freed_allowed_networks` only; false: only to its environment's FreeD output."))
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
        "Address of the job engine's scheduler (Dask distributed), e.g. `tls://scheduler:8786` (with the "
        "`job_tls_*` certificates; `tcp://` on the loopback), whose "
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
    job_tls_ca_file: Path | None = Field(None, description=(
        "PEM certificate of the authority that signs the job engine's certificates. With `job_tls_cert_file` "
        "and `job_tls_key_file`, the scheduler, the workers and the web processes speak TLS to each other "
        "(`tls://` addresses) and each accepts only peers holding a certificate this authority signed "
        "(`fidotrack engine-certs` makes them). Needed when the engine's sockets leave the loopback."))
    job_tls_cert_file: Path | None = Field(None, description=(
        "PEM certificate of this process in the job engine (scheduler, worker or web), signed by "
        "`job_tls_ca_file`."))
    job_tls_key_file: Path | None = Field(None, description="PEM private key of `job_tls_cert_file`.")

    # FreeD receivers a /track connection may name.
    freed_allowed_networks: list[IPvAnyNetwork] = Field([], description=(
        "Networks (CIDR, e.g. `[\"192.168.1.0/24\"]`) where a /track connection's own FreeD receivers may be, "
        "with `freed_connection_receivers`. The environments' FreeD outputs may be anywhere except at loopback, "
        "link-local, multicast, broadcast, unspecified and reserved addresses, which are refused for every "
        "receiver unless a network listed here contains them: with Unreal on the server's own machine, list "
        "`127.0.0.1/32`."))
    freed_resolve_timeout_s: float = Field(2.0, gt=0, le=60, description=(
        "How long the lookup of a FreeD receiver's host name may take; a slower one refuses the receiver "
        "(error `freed`)."))
    freed_resolve_cache_s: float = Field(60.0, ge=0, le=86400, description=(
        "How long the addresses of a FreeD receiver's host name (or the failure to find them) are reused "
        "before the name is looked up again."))

    # Origins allowed to open /track and send state-changing requests.
    allowed_origins: Annotated[tuple[str, ...], NoDecode] = Field((), description=(
        "Origins (`scheme://host[:port]`, comma-separated) of pages that may open /track and send POST, PUT, "
        "PATCH and DELETE requests besides the service's own pages (the origin the request's scheme and Host "
        "header name); `*`: pages of any origin. Requests without an `Origin` header (curl, the Python "
        "client) are not affected."))

    @field_validator("allowed_origins", mode="before")
    @classmethod
    def _allowed_origins(cls, value: object) -> tuple[str, ...]:
        """Each entry as a browser's ``Origin`` header writes it (lower case, no default
        port); refused at start, saying which, when one is not an origin."""
        entries = value.split(",") if isinstance(value, str) else value
        if not isinstance(entries, (list, tuple, set, frozenset)):
            raise ValueError("a comma-separated list of origins (scheme://host[:port]) or *")
        stripped = [str(entry).strip() for entry in entries]
        return tuple(entry if entry == "*" else normalize_origin(entry) for entry in stripped if entry)

    # Slow clients: header and body timeouts, connections per address.
    request_header_timeout_s: float = Field(10.0, gt=0, le=3600, description=(
        "A request's whole header must arrive within this long of its connection's start or of the previous "
        "response's end; else 408 and the connection is closed (an idle connection is just closed)."))
    request_body_timeout_s: float = Field(30.0, gt=0, le=3600, description=(
        "A request body that brings no byte for this long is dropped (408, connection closed). Time the "
        "server itself is not reading does not count."))
    request_body_min_bytes_per_s: int = Field(1024, ge=0, description=(
        "A request body's average rate must stay at least this once it has taken `request_body_timeout_s` "
        "(else 408, connection closed); 0 for no minimum."))
    max_connections_per_address: int = Field(256, ge=1, description=(
        "Most connections one peer address (IPv6: its /64 network) may hold open in one server process, "
        "WebSockets included; its next ones are closed as soon as they are accepted. Behind a proxy every client shares the "
        "proxy's address: set this above the proxy's connections. Lowered at start to a quarter of the "
        "open files the process may have."))

    # Per-key and per-address limits on /track connections and request rate.
    max_track_connections_per_address: int = Field(8, ge=0, description=(
        "Open /track connections one client address may hold, across every server process (0: no limit of its "
        "own). The default, an eighth of `max_track_connections`, covers a machine streaming several cameras "
        "and reconnecting them, and makes one client need eight addresses to hold every slot. IPv6 addresses "
        "count by their /64 network. Behind a proxy, the address is the one the proxy forwards in "
        "`X-Forwarded-For`, taken from the proxies the web server trusts (the variable `FORWARDED_ALLOW_IPS`, "
        "default 127.0.0.1)."))
    max_track_connections_per_key: int = Field(8, ge=0, description=(
        "Open /track connections one API key may hold, across every server process (with `api_keys`; 0: no "
        "limit of its own): a share of `max_track_connections`, as per address. Give each machine its own key, "
        "or raise this for a key many cameras share."))
    request_rate_per_address: float = Field(20.0, ge=0, description=(
        "HTTP requests a second one client address may make, on average (a token bucket; 0: no limit). More "
        "get 429 with `Retry-After`, before the request's key is looked up or its body read. /livez and /readyz "
        "are not counted. The default is ample for the web app and scripts (a /track connection's frames are "
        "messages, not requests) and keeps what one address's admitted requests cost the server to a few "
        "percent of a core."))
    request_burst_per_address: int = Field(100, ge=1, description=(
        "HTTP requests one client address may make at once beyond `request_rate_per_address` (the bucket's "
        "size): a page of the web app loads some 20 files and API calls at once."))
    request_rate_per_key: float = Field(100.0, ge=0, description=(
        "HTTP requests a second one API key may make, on average, from all its addresses together (with "
        "`api_keys`; 0: no limit). More get 429 with `Retry-After`."))
    request_burst_per_key: int = Field(400, ge=1, description="The bucket's size of `request_rate_per_key`.")
    track_open_rate_per_address: float = Field(1.0, ge=0, description=(
        "/track connections a second one client address may open, on average (0: no limit). More are refused "
        "with the error `too_many_requests` and its `retry_after_s`, then close code 1013."))
    track_open_burst_per_address: int = Field(16, ge=1, description=(
        "/track connections one client address may open at once (the bucket's size of "
        "`track_open_rate_per_address`): twice its share of connections."))
    track_open_rate_per_key: float = Field(2.0, ge=0, description=(
        "/track connections a second one API key may open, on average, from all its addresses together (with "
        "`api_keys`; 0: no limit)."))
    track_open_burst_per_key: int = Field(32, ge=1, description="The bucket's size of `track_open_rate_per_key`.")

    # Uploads in flight.
    max_upload_bytes_in_flight: int = Field(1024 * 1024 * 1024, ge=1024, description=(
        "Bytes of survey and training uploads one server process reads at once, each counted from its "
        "Content-Length (else as it arrives): a new upload that would pass it gets 503 with Retry-After before "
        "any of its body is read. An upload alone is always let in (`max_upload_bytes` bounds it)."))

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
