"""The producer side of the job system: what the API uses to store, enqueue, follow and cancel work.

Imported by ``service`` (the HTTP API, the CLI) and by ``workers`` (the job bodies publish their
results with it); never imports either, and never imports numba (the engine's numba-free
``engine.ENGINE_VERSION`` is part of every artifact key). One module per concept:

- ``settings``: the one ``Settings`` class (``IBR_*`` environment variables) of every process;
- ``store/``: the object store interface and its backends (local files, S3);
- ``artifacts``: what lives where in the store -- content-addressed artifacts, scenes, blobs;
- ``ownership``: which API key may see a scene, a dataset or a job;
- ``embedded``: the private Redis server that ``ibr up`` starts;
- ``queue``: the Redis connection, the two queues, timeouts and retry policy, job lookup;
- ``names``: the import paths of the job functions and the job ids (what RQ stores);
- ``payloads``: the one JSON argument of each job, validated again by the worker;
- ``errors``: the exceptions the API maps to HTTP answers;
- ``enqueue``: de-duplicated enqueueing (one job per id under a Redis lock);
- ``status``: the API's view of a job, the job list, the ids active jobs use;
- ``wait``: waiting for a job to end (the one wait of the API);
- ``cancel``: canceling a job (and the jobs of a bake with it);
- ``renders``, ``batches``, ``bakes``, ``walkthroughs``, ``datasets``: keys, enqueueing and
  status of each kind of work; ``scene_outputs``: everything derived from a scene.
"""
