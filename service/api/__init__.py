"""HTTP API: routers, dependencies, error mapping and request limits."""
