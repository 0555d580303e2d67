"""Every module in tests/fixtures/ is a pytest plugin: real Redis, real S3 server, etc."""

import os
import pkgutil

import tests.fixtures

# Worker subprocesses started by tests (tests/fixtures/redis.py, service.up stacks) inherit this:
# no start-up warm-up (workers/warmup.py), which with a cold numba cache (CI's first run) compiles
# every render kernel (minutes) before the first job, longer than those tests wait for it.
# tests/test_worker_warmup.py starts its render worker with IBR_WORKER_WARMUP=true.
os.environ.setdefault("IBR_WORKER_WARMUP", "false")

pytest_plugins = [f"tests.fixtures.{m.name}" for m in pkgutil.iter_modules(tests.fixtures.__path__)]
