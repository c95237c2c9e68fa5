# fidotrack image: slim Python, non-root. One image serves every role, chosen by the
# command: `fidotrack serve` (the API, the default), `fidotrack scheduler` (the job
# engine's scheduler), `fidotrack worker` (job workers); see docs/deployment.md.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    FIDOTRACK_HOST=0.0.0.0 \
    FIDOTRACK_PORT=8000 \
    FIDOTRACK_DATA_DIR=/data \
    NUMBA_CACHE_DIR=/data/numba-cache

# /engine-certs: where compose's engine-certs step writes the job engine's certificates
# (a volume mounted there starts with this folder's owner).
RUN useradd --create-home --uid 10001 fidotrack \
    && mkdir -p /data /engine-certs && chown fidotrack:fidotrack /data /engine-certs

WORKDIR /srv/fidotrack
# Dependencies first so that code changes do not reinstall them.
COPY pyproject.toml README.md ./
COPY app/__init__.py app/__init__.py
# The postgres extra: the driver of FIDOTRACK_DATABASE_URL=postgresql://... (compose.yaml).
RUN pip install --upgrade pip && pip install -e '.[postgres]' && rm -rf /root/.cache
COPY app app
COPY migrations migrations
COPY alembic.ini ./

USER fidotrack
# Uploads live here: the web and the workers must share it, at the same path.
VOLUME ["/data"]
# 8000: the API (serve); 8786: the job scheduler (scheduler).
EXPOSE 8000 8786
# The web role's check; compose.yaml gives the scheduler and the workers their own.
HEALTHCHECK --interval=30s --timeout=3s --start-period=20s --retries=3 \
    CMD python -c "import urllib.request,sys; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/livez', timeout=2).status == 200 else 1)"
CMD ["fidotrack", "serve"]
