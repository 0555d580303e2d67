FROM python:3.11-slim
WORKDIR /app
# libgomp: OpenImageIO / numba runtime; curl-free healthchecks use python
RUN apt-get update && apt-get install -y --no-install-recommends libgomp1 && rm -rf /var/lib/apt/lists/*
COPY pyproject.toml README.md ./
COPY api_schemas api_schemas
COPY engine engine
COPY workers workers
COPY service service
COPY samples samples
RUN pip install --no-cache-dir .
ENV NUMBA_CACHE_DIR=/data/numba-cache \
    IBR_DATA_DIR=/data
RUN mkdir -p /data/numba-cache
EXPOSE 8000
ENTRYPOINT ["ibr"]
