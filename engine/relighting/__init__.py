"""Relighting an object from an illumination dataset (docs/relighting.md).

Modules, in the order a relight uses them:

- ``dataset``: the illumination dataset (K images, one light each, the surface points) and
  ``points_from_depth``;
- ``grid``: light directions deduplicated and triangulated on the sphere, the cube-map grid and
  the direction lookup;
- ``bake``: ``bake_dataset`` -> ``BakedDataset`` (the store, float16 or float32, tiled or
  pixel-major), the bake's kernels;
- ``compress``: the low-rank store (a compressed bake);
- ``lights``: the relighting's light specs (point, directional, rect, environment) and their
  expansion into the kernel's lights;
- ``kernel``: the relight kernel and its float16 / SIMD intrinsics;
- ``relight``: ``relight()``, the public entry point, and ``RelightResult``;
- ``generate``: datasets rendered from a scene, ground truth under any lights;
- ``composite``: a relit object over a background plate.
"""
