"""Benchmarks and cross-checks of the engine (run as ``python -m bench.<name>``).

- ``raycast_throughput``: raw Embree vs the reference renderer's ray throughput.
- ``embree_binding``: the engine's Embree kernels (engine/embree.py) against the ``embreex`` binding.
- ``mitsuba_bridge``: the same scene for Mitsuba 3 (convert a runtime scene, or load the
  Mitsuba-native scene files from ``../shared/data``).
- ``mitsuba_crosscheck``: the reference renderer against Mitsuba 3's ``direct`` and ``path``
  integrators; writes ``docs/accuracy-reference.md`` and ``docs/img/crosscheck/``.
- ``docs_writer``: shared helper to update a marked block of a Markdown page.
"""
