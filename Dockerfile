# STREP Studio: the web service (REST API on 8000, viser 3D viewer on 8080).
#   docker build -t strep-studio .                       # CPU torch (default)
#   docker build -t strep-studio --build-arg TORCH_INDEX=https://download.pytorch.org/whl/cu124 .
#   docker run -p 8000:8000 -p 8080:8080 -e STREP_API_TOKEN=change-me -v strep-data:/data strep-studio
FROM python:3.11-slim

ARG TORCH_VERSION=2.13.0
# The wheel index torch comes from: the CPU build by default, a CUDA index for GPUs.
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    STREP_DATA_DIR=/data \
    STREP_HOST=0.0.0.0 \
    STREP_PORT=8000 \
    STREP_VIEWER_PORT=8080

# Open3D's wheel links libgomp; curl serves the health check. Versions float with the base
# image's Debian release on purpose (pinned Debian versions vanish from the mirrors).
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 curl \
    && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 1000 strep \
    && mkdir -p /data /app \
    && chown strep:strep /data /app

WORKDIR /app
RUN pip install --index-url "${TORCH_INDEX}" "torch==${TORCH_VERSION}"

COPY --chown=strep:strep pyproject.toml README.md ./
COPY --chown=strep:strep strep_core ./strep_core
COPY --chown=strep:strep strep_bench ./strep_bench
COPY --chown=strep:strep strep_cli ./strep_cli
COPY --chown=strep:strep app ./app
COPY --chown=strep:strep static ./static
COPY --chown=strep:strep sample_sequences ./sample_sequences
RUN pip install -e .

USER 1000:1000
VOLUME ["/data"]
EXPOSE 8000 8080

# Bound to 0.0.0.0 the service refuses to start without STREP_API_TOKEN (set it at docker run).
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["sh", "-c", "curl -fsS -H \"Authorization: Bearer ${STREP_API_TOKEN}\" http://127.0.0.1:${STREP_PORT}/api/health"]

CMD ["strep", "serve", "--host", "0.0.0.0", "--port", "8000", "--data-dir", "/data"]
