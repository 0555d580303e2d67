FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY api_schemas api_schemas
COPY engine engine
COPY workers workers
COPY service service
COPY samples samples
RUN pip install --no-cache-dir .
ENV NUMBA_CACHE_DIR=/tmp/numba-cache
ENTRYPOINT ["ibr"]
