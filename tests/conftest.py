"""Every module in tests/fixtures/ is a pytest plugin: real Redis, real S3 server, etc."""

import pkgutil

import tests.fixtures

pytest_plugins = [f"tests.fixtures.{m.name}" for m in pkgutil.iter_modules(tests.fixtures.__path__)]
