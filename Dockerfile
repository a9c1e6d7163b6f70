# QuickNav: one image for the API (`quicknav serve`: HTTP + gRPC rollouts), workers (`quicknav
# worker`) and every other `quicknav` command.
#
#   docker build -t quicknav:cpu .                              # CPU JAX
#   docker build -t quicknav:cuda --build-arg JAX_EXTRA=cuda .  # CUDA 13 JAX for GPU workers
#   docker run --rm -p 8000:8000 -p 50051:50051 quicknav:cpu    # API + in-process worker, SQLite in /data
#
# The CUDA libraries come as wheels (jax[cuda13]), so the base stays python:slim; the host needs only
# the NVIDIA driver and the NVIDIA container toolkit. Needs BuildKit (the default builder since
# Docker 23) for the RUN --mount cache and bind mounts. See deploy/README.md.

ARG PYTHON_IMAGE=python:3.11-slim-bookworm

# uv, pinned; only its binary is used
FROM ghcr.io/astral-sh/uv:0.13.9 AS uv

FROM ${PYTHON_IMAGE} AS builder
COPY --from=uv /uv /uvx /bin/
# bytecode compiled at build time (faster start); copy, not hardlink, out of the cache mount;
# the slim image's /usr/local/bin/python3.11 is the interpreter, never a downloaded one
ENV UV_COMPILE_BYTECODE=1 \
    UV_LINK_MODE=copy \
    UV_PYTHON_DOWNLOADS=0 \
    UV_PROJECT_ENVIRONMENT=/app/.venv
WORKDIR /app

# empty: CPU JAX; "cuda": the `cuda` extra of pyproject.toml (jax[cuda13]; "cuda12" for older drivers)
ARG JAX_EXTRA=""

# 1. Third-party dependencies only, from the lock: this layer is rebuilt when uv.lock or a
#    pyproject.toml changes, not when code does. The root project depends on the workspace member
#    clients/ (quicknav-client), so uv needs its pyproject.toml to read the workspace.
RUN --mount=type=cache,target=/root/.cache/uv \
    --mount=type=bind,source=uv.lock,target=uv.lock \
    --mount=type=bind,source=pyproject.toml,target=pyproject.toml \
    --mount=type=bind,source=clients/pyproject.toml,target=clients/pyproject.toml \
    uv sync --locked --no-dev --extra service --no-install-workspace ${JAX_EXTRA:+--extra "$JAX_EXTRA"}

# 2. The project and the client package it depends on. --no-editable installs both into the venv
#    as wheels (the client's gRPC stubs are generated here by clients/hatch_build.py from proto/,
#    with grpcio-tools from its [build-system]), so the venv alone is the application. The
#    `service` extra brings the HTTP API, the gRPC server and the job stores.
COPY pyproject.toml uv.lock README.md ./
COPY proto ./proto
COPY clients ./clients
COPY quicknav_core ./quicknav_core
COPY quicknav_cli ./quicknav_cli
COPY quicknav_service ./quicknav_service
RUN --mount=type=cache,target=/root/.cache/uv \
    uv sync --locked --no-dev --extra service --no-editable ${JAX_EXTRA:+--extra "$JAX_EXTRA"}


FROM ${PYTHON_IMAGE} AS runtime
# a fixed numeric uid, so orchestrators can check runAsNonRoot and volumes can be chowned to it
RUN groupadd --gid 10001 quicknav \
    && useradd --uid 10001 --gid quicknav --create-home --home-dir /home/quicknav quicknav \
    && mkdir -p /data \
    && chown quicknav:quicknav /data
# root-owned and read-only for the service user: the code cannot be changed by the process running it
COPY --from=builder /app/.venv /app/.venv
ENV PATH="/app/.venv/bin:$PATH" \
    PYTHONUNBUFFERED=1 \
    QUICKNAV_DATA_DIR=/data \
    QUICKNAV_HOST=0.0.0.0
# /data: jobs.db (embedded store), artifacts/, jax-cache/; one-off commands write their runs here too
WORKDIR /data
USER 10001:10001

# HTTP API (QUICKNAV_PORT) and gRPC rollouts (QUICKNAV_GRPC_PORT)
EXPOSE 8000 50051

# liveness of the HTTP API; python's urllib so the slim image needs no curl
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:' + os.environ.get('QUICKNAV_PORT', '8000') + '/healthz', timeout=4)"]

CMD ["quicknav", "serve"]
