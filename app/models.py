"""SQLAlchemy 2 models: environments, their surveyed maps, classifiers and jobs.

Arrays are kept as ``.npy`` bytes (``allow_pickle=False``) or small JSON, never pickle.
The schema only changes through an Alembic migration; ``tests/test_migrations.py``
fails when these models and the migrations disagree.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    CheckConstraint,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    LargeBinary,
    String,
    Text,
)
from sqlalchemy.orm import Mapped, mapped_column, relationship

from app.db import Base, utcnow
from app.schemas import JobStatus


class Environment(Base):
    """A place with targets on its walls: one marker family, one printed size, one map."""

    __tablename__ = "environments"
    # AUTOINCREMENT: ids of deleted environments are never handed out again.
    __table_args__ = (
        CheckConstraint("marker_size_m > 0", name="marker_size_positive"),
        {"sqlite_autoincrement": True},
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    marker_size_m: Mapped[float] = mapped_column(Float)
    marker_family: Mapped[str] = mapped_column(String(32), default="fido3x3")
    classifier_id: Mapped[int | None] = mapped_column(
        ForeignKey("classifiers.id", ondelete="SET NULL"), nullable=True, index=True
    )
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(
        DateTime(timezone=True), default=utcnow, onupdate=utcnow
    )

    map: Mapped[SurveyMap | None] = relationship(
        back_populates="environment", cascade="all, delete-orphan", passive_deletes=True
    )


class SurveyMap(Base):
    """The surveyed (or imported) 3D disc positions of an environment and its camera.

    One per environment; a new survey or import replaces it in one transaction.
    ``document`` is the map document (``app.schemas.MapDocument``), validated before it is stored.
    ``revision`` grows by one with every change (the map's ``ETag``; ``If-Match`` names it).
    """

    __tablename__ = "maps"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    environment_id: Mapped[int] = mapped_column(
        ForeignKey("environments.id", ondelete="CASCADE"), unique=True
    )
    frame: Mapped[str] = mapped_column(String(16))
    n_targets: Mapped[int] = mapped_column(Integer)
    rms_px: Mapped[float | None] = mapped_column(Float, nullable=True)
    survey_job_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    document: Mapped[dict[str, Any]] = mapped_column(JSON)
    revision: Mapped[int] = mapped_column(Integer, default=1)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(
        DateTime(timezone=True), default=utcnow, onupdate=utcnow
    )

    environment: Mapped[Environment] = relationship(back_populates="map")


class MapVersion(Base):
    """A map an environment had before a change replaced it (an import, a survey, an
    alignment, a restore): kept so that no single call loses a survey. The newest
    ``MAP_VERSIONS_KEPT`` of each environment are kept."""

    __tablename__ = "map_versions"
    __table_args__ = {"sqlite_autoincrement": True}

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    environment_id: Mapped[int] = mapped_column(ForeignKey("environments.id", ondelete="CASCADE"), index=True)
    frame: Mapped[str] = mapped_column(String(16))
    n_targets: Mapped[int] = mapped_column(Integer)
    survey_job_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    document: Mapped[dict[str, Any]] = mapped_column(JSON)
    # The revision the map had; None for maps kept before revisions were counted.
    revision: Mapped[int | None] = mapped_column(Integer, nullable=True)
    replaced_by: Mapped[str] = mapped_column(String(16))
    replaced_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class FreeDReceiver(Base):
    """Where an environment's /track connections send their poses as FreeD packets."""

    __tablename__ = "freed_receivers"

    environment_id: Mapped[int] = mapped_column(ForeignKey("environments.id", ondelete="CASCADE"),
                                                primary_key=True)
    host: Mapped[str] = mapped_column(String(253))
    port: Mapped[int] = mapped_column(Integer)
    camera_id: Mapped[int] = mapped_column(Integer, default=1)
    enabled: Mapped[bool] = mapped_column(Boolean, default=True)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow, onupdate=utcnow)


class Classifier(Base):
    """A trained disc detector (paper §4): stage-1 parameters and condensed prototypes."""

    __tablename__ = "classifiers"
    __table_args__ = {"sqlite_autoincrement": True}

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    is_default: Mapped[bool] = mapped_column(Boolean, default=False)
    source: Mapped[str] = mapped_column(String(32), default="builtin")
    training_stats: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    training_job_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    arrays: Mapped[list[ClassifierArray]] = relationship(
        cascade="all, delete-orphan", passive_deletes=True
    )


class ClassifierArray(Base):
    """One named array of a classifier, as ``.npy`` bytes."""

    __tablename__ = "classifier_arrays"

    classifier_id: Mapped[int] = mapped_column(
        ForeignKey("classifiers.id", ondelete="CASCADE"), primary_key=True
    )
    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    npy: Mapped[bytes] = mapped_column(LargeBinary)


class Job(Base):
    """Long work (surveys, classifier training) with its stage, progress and outcome."""

    __tablename__ = "jobs"
    __table_args__ = (
        CheckConstraint(f"status IN ({', '.join(repr(s.value) for s in JobStatus)})", name="status_known"),
        CheckConstraint("progress >= 0 AND progress <= 1", name="progress_fraction"),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    kind: Mapped[str] = mapped_column(String(32))
    status: Mapped[str] = mapped_column(String(16), default=JobStatus.QUEUED.value, index=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    stage: Mapped[str] = mapped_column(String(64), default="queued")
    message: Mapped[str] = mapped_column(Text, default="")
    environment_id: Mapped[int | None] = mapped_column(
        ForeignKey("environments.id", ondelete="CASCADE"), nullable=True, index=True
    )
    # The web process that owns the job ("host:pid"): at start a process fails only the
    # jobs of runners that are gone, not those of a sibling worker.
    runner: Mapped[str | None] = mapped_column(String(96), nullable=True)
    # Each run of the job (a worker that died has its job run again) takes the next
    # attempt; only the newest attempt may report progress or finish the job.
    attempt: Mapped[int] = mapped_column(Integer, default=0)
    # The engine's worker running the newest attempt, and when it last said it was alive:
    # a job whose worker fell silent is failed by any web process, on any machine.
    worker: Mapped[str | None] = mapped_column(String(128), nullable=True)
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)


class TrackConnection(Base):
    """An open /track connection, held by the server process that serves it: the limit on
    open connections counts these rows, so it holds across processes and machines. A
    process renews its rows' ``seen_at``; rows of a process that died go stale and stop
    counting."""

    __tablename__ = "track_connections"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    server: Mapped[str] = mapped_column(String(96), index=True)
    environment_id: Mapped[int] = mapped_column(ForeignKey("environments.id", ondelete="CASCADE"), index=True)
    opened_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    seen_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow, index=True)
    # Who holds it, for the limits per client address and per API key (None: not known).
    client_address: Mapped[str | None] = mapped_column(String(64), nullable=True, index=True)
    key_id: Mapped[int | None] = mapped_column(Integer, nullable=True, index=True)


class ApiKey(Base):
    """An API key: only its SHA-256 is stored; ``prefix`` (public) finds the row and the
    hash is compared in constant time. Scopes: read, track, admin."""

    __tablename__ = "api_keys"
    __table_args__ = ({"sqlite_autoincrement": True},)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    prefix: Mapped[str] = mapped_column(String(16), unique=True)
    key_sha256: Mapped[str] = mapped_column(String(64))
    scopes: Mapped[list[str]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
