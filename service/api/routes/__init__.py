"""One router per resource."""

from service.api.routes import artifacts, batches, health, jobs, renders, scenes

__all__ = ["artifacts", "batches", "health", "jobs", "renders", "scenes"]
