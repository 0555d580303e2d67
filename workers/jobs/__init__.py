"""RQ job functions, enqueued by import path with one JSON-safe dict argument.

One module per kind of work: ``render`` (the render queue's renders), ``bake`` (a scene bake's plan,
parts and merge), ``datasets`` (dataset generation and bake, relights, composites), ``walkthrough``
(walkthrough bake, frame chunks, video); ``common`` holds what they share. The dotted paths of the
job functions are named in ``producer.names`` (RQ stores them in queued jobs, so they never move
without an alias) and the payloads they validate are ``producer.payloads``.
"""
