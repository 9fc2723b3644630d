# catalign's CPU image: serves model_store/ (weights and default library) over HTTP on 8000 and
# gRPC on 50051 as an unprivileged user. scripts/build_image.sh builds it (Docker or Podman)
# from a wheelhouse made on the host; a plain build without wheelhouse/ installs from the index.
#
#   scripts/build_image.sh --tag catalign
#   docker run -p 8000:8000 -p 50051:50051 -e CATALIGN_API_KEY_FILE=/run/secrets/catalign-key \
#       -v "$PWD/catalign-key:/run/secrets/catalign-key:ro" catalign
ARG BASE=python:3.11-slim
FROM ${BASE}

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PATH=/app/.venv/bin:$PATH

# The shared libraries open3d links against; the Debian base of build_image.sh has them, a
# python:3.11-slim base gets them with apt.
RUN set -eu; \
    for lib in libGL.so.1 libEGL.so.1 libX11.so.6 libudev.so.1 libusb-1.0.so.0 libidn2.so.0; do \
        ldconfig -p | grep -q "$lib" || missing=1; \
    done; \
    if [ -n "${missing:-}" ]; then \
        apt-get update -qq; \
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
            libgl1 libegl1 libx11-6 libudev1 libusb-1.0-0 libidn2-0 >/dev/null; \
        rm -rf /var/lib/apt/lists/*; \
    fi; \
    useradd --create-home --uid 10001 catalign

WORKDIR /app
COPY pyproject.toml README.md ./
COPY client/ client/
COPY service/ service/
# The wheelhouse is read through a mount of the build context, so it never becomes a layer.
# torch first, pinned, so that nothing later pulls a multi-GB CUDA build. The package stays
# editable: its default model_store/ is found beside its sources; the SDK's sources and the
# build's inputs go. The imports fail the build, not the first start, on a missing library.
RUN --mount=type=bind,target=/context \
    set -eu; \
    if ls /context/wheelhouse/*.whl >/dev/null 2>&1; then \
        export PIP_NO_INDEX=1 PIP_FIND_LINKS=/context/wheelhouse; \
    else \
        export PIP_EXTRA_INDEX_URL=https://download.pytorch.org/whl/cpu; \
    fi; \
    python3 -m venv .venv; \
    .venv/bin/pip install --quiet torch==2.13.0; \
    .venv/bin/pip install --quiet -e ".[serve]" ./client; \
    rm -rf client README.md pyproject.toml; \
    .venv/bin/python -m compileall -q service; \
    .venv/bin/python -c "import open3d, torch, catalign.api.app"

# The library stays writable by the server (POST/DELETE /models; start with --read-only to
# refuse changes).
COPY --chown=catalign:catalign model_store/ model_store/
USER catalign

EXPOSE 8000 50051
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:' + os.environ.get('CATALIGN_PORT', '8000') + '/health/ready', timeout=4)"]
CMD ["catalign", "serve", "--host", "0.0.0.0"]
