"""The worker runtime: the processes that run the queued jobs.

``runner`` (the RQ worker processes and their retry policy), ``warmup`` (a render worker compiles or
loads every kernel before taking jobs), ``jobs/`` (the job bodies), ``cache`` (warm renderers and
loaded scenes), ``scene_loader`` (an ``api_schemas.Scene`` -> the engine's runtime scene). What the
API uses to enqueue and follow the jobs is ``producer``; workers import it, never the reverse.
"""
