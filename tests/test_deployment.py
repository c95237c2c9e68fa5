"""The deployment files (compose.yaml, Dockerfile) hold together without a Docker daemon:
every role is the same image running a real `fidotrack` command, the web and the workers
share the uploads at the data directory's path and reach the scheduler over TLS with the
certificates made for them, the database URL matches the database service, and the image
installs the PostgreSQL driver. docs/deployment.md describes the topology."""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
import tomllib
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import yaml

from app.cli import build_parser
from app.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
#: The services that run the fidotrack image, and the subcommand each runs.
ROLES = {"web": "serve", "scheduler": "scheduler", "worker": "worker"}
#: The service that makes the job engine's certificates.
CERTS = "engine-certs"
#: The settings that give a process of the job engine its TLS files.
ENGINE_TLS = ("FIDOTRACK_JOB_TLS_CA_FILE", "FIDOTRACK_JOB_TLS_CERT_FILE", "FIDOTRACK_JOB_TLS_KEY_FILE")
#: `${NAME}`, `${NAME:-default}` or `${NAME-default}` in a compose file.
VARIABLE = re.compile(r"\$\{(?P<name>\w+)(?::?-(?P<default>[^}]*))?\}")


def _interpolate(value: str) -> str:
    """A compose value as an unconfigured machine gets it: every variable at its default."""
    return VARIABLE.sub(lambda m: m["default"] or "", value)


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    document = yaml.safe_load((ROOT / "compose.yaml").read_text(encoding="utf-8"))
    assert isinstance(document, dict) and isinstance(document.get("services"), dict)
    return document


@pytest.fixture(scope="module")
def dockerfile() -> str:
    # Continuation lines joined, so that each instruction is one line.
    return (ROOT / "Dockerfile").read_text(encoding="utf-8").replace("\\\n", " ")


def _service(compose: dict[str, Any], name: str) -> dict[str, Any]:
    assert name in compose["services"], f"compose.yaml has no service {name!r}"
    return compose["services"][name]


def _environment(service: dict[str, Any]) -> dict[str, str]:
    env = service.get("environment", {})
    if isinstance(env, list):  # the `- NAME=value` form
        env = dict(item.split("=", 1) for item in env)
    return {name: _interpolate(str(value)) for name, value in env.items()}


def _command(service: dict[str, Any]) -> list[str]:
    command = service.get("command")
    assert command, "the service names no command (the image's default would run the API)"
    return shlex.split(command) if isinstance(command, str) else [str(part) for part in command]


def _parse(command: list[str]) -> argparse.Namespace:
    """`command` (``fidotrack ...``) as the fidotrack command line parses it."""
    assert command[0] == "fidotrack", command
    errors = io.StringIO()
    try:
        with contextlib.redirect_stderr(errors):
            return build_parser().parse_args(command[1:])
    except SystemExit:
        pytest.fail(f"`{shlex.join(command)}` is not a fidotrack command: {errors.getvalue().strip()}")


def _mounts(service: dict[str, Any]) -> dict[str, str]:
    """The service's volumes as {path in the container: source}."""
    mounts = {}
    for volume in service.get("volumes", []):
        if isinstance(volume, str):
            source, target = volume.split(":")[:2]
        else:
            source, target = volume.get("source", ""), volume["target"]
        mounts[target] = source
    return mounts


def _dockerfile_instructions(dockerfile: str, keyword: str) -> list[str]:
    return [line.split(None, 1)[1].strip() for line in dockerfile.splitlines()
            if line.strip().upper().startswith(keyword + " ")]


def test_every_fidotrack_role_runs_the_same_image(compose: dict[str, Any]) -> None:
    """One build for the web, the scheduler and the workers: they exchange pickled job
    code, which works only between the same versions."""
    builds = {name: (_service(compose, name).get("build"), _service(compose, name).get("image")) for name in ROLES}
    assert len(set(map(repr, builds.values()))) == 1, builds
    build, _ = builds["web"]
    context = build if isinstance(build, str) else build.get("context", ".")
    assert (ROOT / context / "Dockerfile").is_file()


@pytest.mark.parametrize("role", sorted(ROLES))
def test_each_role_runs_a_fidotrack_command(compose: dict[str, Any], role: str) -> None:
    """The commands compose runs exist as `fidotrack` subcommands with these options (a
    typo would leave the container restarting)."""
    args = _parse(_command(_service(compose, role)))
    assert args.command == ROLES[role]


def test_the_web_runs_two_server_processes_on_the_published_port(compose: dict[str, Any]) -> None:
    web = _service(compose, "web")
    assert _parse(_command(web)).workers == 2
    port = _environment(web).get("FIDOTRACK_PORT", "8000")
    published = [str(p) for p in web.get("ports", [])]
    assert any(p.rsplit(":", 1)[-1] == port for p in published), (published, port)


def test_web_and_workers_share_the_uploads_at_the_data_directory(compose: dict[str, Any]) -> None:
    """A survey's uploads are written by a web process and read by a worker under
    $FIDOTRACK_DATA_DIR/uploads/<job id>: one named volume, at that path in both."""
    sources = {}
    for role in ("web", "worker"):
        service = _service(compose, role)
        data_dir = _environment(service).get("FIDOTRACK_DATA_DIR")
        assert data_dir, f"{role} does not set FIDOTRACK_DATA_DIR"
        mounts = _mounts(service)
        assert data_dir in mounts, f"{role} mounts nothing at FIDOTRACK_DATA_DIR={data_dir}: {mounts}"
        sources[role] = (mounts[data_dir], data_dir)
    assert sources["web"] == sources["worker"], sources
    volume = sources["web"][0]
    assert volume in (compose.get("volumes") or {}), f"{volume!r} is not a named volume of compose.yaml"


def test_the_shared_data_directory_is_the_images_volume(compose: dict[str, Any], dockerfile: str) -> None:
    """The image's own data directory and volume are the path compose mounts, so the image
    alone (`docker run -v ...:/data`) and compose keep data in the same place."""
    env = " ".join(_dockerfile_instructions(dockerfile, "ENV"))
    image_data_dir = re.search(r"FIDOTRACK_DATA_DIR=(\S+)", env)
    assert image_data_dir is not None
    assert image_data_dir[1] in " ".join(_dockerfile_instructions(dockerfile, "VOLUME"))
    assert _environment(_service(compose, "web"))["FIDOTRACK_DATA_DIR"] == image_data_dir[1]


def test_web_and_workers_reach_the_scheduler_service(compose: dict[str, Any]) -> None:
    """FIDOTRACK_JOB_SCHEDULER of the web (and the workers' address) is the scheduler
    service at the port it listens on, over TLS."""
    scheduler = _parse(_command(_service(compose, "scheduler")))
    expected = f"tls://scheduler:{scheduler.port}"
    assert _environment(_service(compose, "web")).get("FIDOTRACK_JOB_SCHEDULER") == expected
    worker = _service(compose, "worker")
    address = _parse(_command(worker)).scheduler or _environment(worker).get("FIDOTRACK_JOB_SCHEDULER")
    assert address == expected
    assert scheduler.host == "0.0.0.0"  # (127.0.0.1 would refuse the other containers)
    assert _parse(_command(worker)).host == "0.0.0.0"  # (the scheduler and the other workers connect to it)


def test_every_role_agrees_on_how_often_a_job_runs_again(compose: dict[str, Any]) -> None:
    """Workers count a job's attempts, the web fails silent jobs after the lease, the
    scheduler re-runs a dead worker's task: the same job settings everywhere, and no
    engine setting of the scheduler's own that would override what `fidotrack scheduler`
    derives from them."""
    names = ("FIDOTRACK_JOB_ATTEMPTS", "FIDOTRACK_JOB_LEASE_S", "FIDOTRACK_JOB_HEARTBEAT_S")
    settings = {role: {n: _environment(_service(compose, role)).get(n) for n in names} for role in ROLES}
    assert len(set(map(repr, settings.values()))) == 1, settings
    assert not [name for name in _environment(_service(compose, "scheduler")) if name.startswith("DASK_")]


def test_the_engine_certificates_are_made_before_the_engine_starts(compose: dict[str, Any],
                                                                    dockerfile: str) -> None:
    """A one-shot step of the same image makes them into a named volume, once (a restart
    keeps them), as the image's user, before the scheduler (and so the workers and the
    web, which wait for it) starts."""
    certs = _service(compose, CERTS)
    args = _parse(_command(certs))
    assert args.command == "engine-certs" and args.if_missing
    assert (certs.get("build"), certs.get("image")) == (_service(compose, "web").get("build"),
                                                        _service(compose, "web").get("image"))
    assert str(certs.get("restart")) == "no"
    out = str(args.out)
    assert _mounts(certs).get(out) in (compose.get("volumes") or {}), _mounts(certs)
    assert _service(compose, "scheduler")["depends_on"][CERTS]["condition"] == "service_completed_successfully"
    # A fresh named volume takes the owner of the image's folder it is mounted on.
    assert any(out in run and "chown" in run and "fidotrack" in run
               for run in _dockerfile_instructions(dockerfile, "RUN")), out


@pytest.mark.parametrize("role", sorted(ROLES))
def test_each_role_of_the_engine_speaks_tls_with_its_own_certificate(compose: dict[str, Any], role: str) -> None:
    """The containers talk across a network: no role runs with --insecure, each has the
    authority's certificate and its own certificate and key, from the volume the
    certificates step writes, mounted read-only."""
    service = _service(compose, role)
    args = _parse(_command(service))
    assert not getattr(args, "insecure", False)
    env = _environment(service)
    assert all(env.get(name) for name in ENGINE_TLS), {name: env.get(name) for name in ENGINE_TLS}
    out = str(_parse(_command(_service(compose, CERTS))).out)
    ca, cert, key = (Path(env[name]) for name in ENGINE_TLS)
    assert (ca, cert, key) == (Path(out) / "ca.pem", Path(out) / f"{role}.pem", Path(out) / f"{role}-key.pem")
    volumes = [v for v in service.get("volumes", []) if isinstance(v, str) and v.split(":")[1] == out]
    assert len(volumes) == 1 and volumes[0].split(":")[0] == _mounts(_service(compose, CERTS))[out]
    assert volumes[0].endswith(":ro"), volumes


def test_the_roles_certificates_are_the_ones_engine_certs_makes(tmp_path: Path) -> None:
    from app.services.jobs.certs import make_engine_certs

    issued = make_engine_certs(tmp_path / "certs")
    assert sorted(issued.certs) == sorted(ROLES)
    assert make_engine_certs(tmp_path / "certs", if_missing=True) == issued
    with pytest.raises(FileExistsError):
        make_engine_certs(tmp_path / "certs")


@pytest.mark.parametrize("role", sorted(ROLES))
def test_each_roles_settings_are_valid(compose: dict[str, Any], role: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The FIDOTRACK_* values compose gives start the service (a bad one stops it at start)."""
    for name, value in _environment(_service(compose, role)).items():
        if name.startswith("FIDOTRACK_"):
            monkeypatch.setenv(name, value)
    Settings()


def test_the_database_url_names_the_database_service(compose: dict[str, Any]) -> None:
    """Web and workers log in to the db service with the user, password and database it
    is created with."""
    db = _environment(_service(compose, "db"))
    for role in ("web", "worker"):
        url = urlsplit(_environment(_service(compose, role))["FIDOTRACK_DATABASE_URL"])
        assert url.scheme in ("postgresql", "postgres", "postgresql+psycopg")
        assert (url.hostname, url.port or 5432) == ("db", 5432)
        assert (url.username, url.password, url.path.lstrip("/")) == (
            db["POSTGRES_USER"], db["POSTGRES_PASSWORD"], db.get("POSTGRES_DB", db["POSTGRES_USER"]))


def test_the_database_password_can_be_set_without_editing_the_file(compose: dict[str, Any]) -> None:
    raw = str(_service(compose, "db")["environment"]["POSTGRES_PASSWORD"])
    match = VARIABLE.fullmatch(raw)
    assert match is not None, "POSTGRES_PASSWORD should come from a variable (with a default for local use)"
    for role in ("web", "worker"):
        assert f"${{{match['name']}" in str(_service(compose, role)["environment"]["FIDOTRACK_DATABASE_URL"])


def test_the_database_keeps_its_data_and_says_when_it_is_ready(compose: dict[str, Any]) -> None:
    db = _service(compose, "db")
    assert str(db["image"]).startswith("postgres:16")
    source = _mounts(db).get("/var/lib/postgresql/data")
    assert source in (compose.get("volumes") or {}), "the database's files should be in a named volume"
    assert "pg_isready" in " ".join(map(str, db["healthcheck"]["test"]))


@pytest.mark.parametrize("role", ["web", "worker"])
def test_web_and_workers_start_once_the_database_is_healthy(compose: dict[str, Any], role: str) -> None:
    depends = _service(compose, role).get("depends_on")
    assert isinstance(depends, dict), "depends_on with conditions"
    assert depends.get("db", {}).get("condition") == "service_healthy"
    assert "scheduler" in depends


@pytest.mark.parametrize("role", ["scheduler", "worker"])
def test_roles_without_the_api_do_not_use_the_images_api_check(compose: dict[str, Any], role: str,
                                                               dockerfile: str) -> None:
    """The image's health check asks the API at :8000; the scheduler and the workers do not
    serve it, and would show as unhealthy forever with it."""
    assert "/livez" in " ".join(_dockerfile_instructions(dockerfile, "HEALTHCHECK"))
    check = _service(compose, role).get("healthcheck")
    assert check is not None, f"{role} inherits the image's API health check"
    assert check.get("disable") or "8000" not in " ".join(map(str, check.get("test", [])))


def test_more_than_one_worker(compose: dict[str, Any]) -> None:
    """Jobs run one per worker process: two replicas run two at once, and one dying
    leaves another to run its job again."""
    worker = _service(compose, "worker")
    replicas = worker.get("deploy", {}).get("replicas", 1)
    assert replicas * _parse(_command(worker)).nworkers >= 2


def test_no_broker_service(compose: dict[str, Any]) -> None:
    """The job scheduler is the broker: no Redis or RabbitMQ to run and secure."""
    images = [str(s.get("image", "")) for s in compose["services"].values()]
    assert not [i for i in images if re.match(r"(redis|rabbitmq)\b", i)]


def test_the_image_installs_the_postgresql_driver(dockerfile: str) -> None:
    installs = [run for run in _dockerfile_instructions(dockerfile, "RUN") if "pip install" in run]
    extras = {extra.strip() for run in installs for group in re.findall(r"\.\[([\w,\s-]+)\]", run)
              for extra in group.split(",")}
    assert "postgres" in extras, installs
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    assert any(dep.startswith("psycopg") for dep in project["optional-dependencies"]["postgres"])


def test_the_image_runs_as_a_user_and_serves_by_default(dockerfile: str) -> None:
    users = _dockerfile_instructions(dockerfile, "USER")
    assert users and users[-1] not in ("root", "0")
    command = yaml.safe_load(_dockerfile_instructions(dockerfile, "CMD")[-1])  # (a JSON array)
    assert _parse(command).command == "serve"
