# catalign's CPU image: serves model_store/ (weights and default library) over HTTP on 8000 and
# gRPC on 50051. Set-up is the README's (scripts/setup.sh: libusb-1.0-0 with apt, then .venv
# with torch first), run as root at build time; the server runs as an unprivileged user.
#
#   docker build -t catalign .
#   docker run -p 8000:8000 -p 50051:50051 -e CATALIGN_API_KEY_FILE=/run/secrets/key -v ...:/run/secrets/key:ro catalign
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_EXTRA_INDEX_URL=https://download.pytorch.org/whl/cpu \
    PYTHON=python3.11

WORKDIR /app
# What scripts/setup.sh installs from (the package is installed in editable mode).
COPY pyproject.toml README.md ./
COPY scripts/setup.sh scripts/setup.sh
COPY client/ client/
COPY service/ service/
RUN bash scripts/setup.sh && rm -rf /var/lib/apt/lists/*

COPY model_store/ model_store/
# The library stays writable by the server (POST/DELETE /models; start with --read-only to
# refuse changes).
RUN useradd --create-home --uid 10001 catalign && chown -R catalign:catalign /app/model_store
USER catalign

ENV PATH=/app/.venv/bin:$PATH
EXPOSE 8000 50051
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:' + os.environ.get('CATALIGN_PORT', '8000') + '/health/ready', timeout=4)"]
CMD ["catalign", "serve", "--host", "0.0.0.0"]
