FROM python:3.11-slim
WORKDIR /app
# libgomp: OpenImageIO / numba runtime; curl-free healthchecks use python
RUN apt-get update && apt-get install -y --no-install-recommends libgomp1 && rm -rf /var/lib/apt/lists/*
COPY pyproject.toml README.md constraints.txt ./
COPY api_schemas api_schemas
COPY engine engine
COPY producer producer
COPY workers workers
COPY service service
COPY samples samples
COPY ibr_client ibr_client
# the runtime only: pyproject.toml's dev extras (tests, Mitsuba, Playwright, lint) stay out of the image
RUN pip install --no-cache-dir -c constraints.txt .
# numba's disk cache ships in the image: the warm-up (workers/warmup.py) runs every render-job
# kernel (and the LDC / LLF / dataset bake kernels it needs) once at build time, so workers load
# instead of compile (~5 s instead of minutes at start-up; docs/service-design.md, "Worker start-up
# and warm-up"). The cache is keyed by CPU model: on hosts with another CPU than the build host's,
# the render worker's start-up warm-up compiles again (before it takes jobs).
ENV NUMBA_CACHE_DIR=/opt/ibr/numba-cache \
    IBR_DATA_DIR=/data
RUN mkdir -p /data "$NUMBA_CACHE_DIR" && python -m workers.warmup && chmod -R a+rwX "$NUMBA_CACHE_DIR"
EXPOSE 8000
ENTRYPOINT ["ibr"]
