"""Relighting an object from an illumination dataset (docs/relighting.md).

Modules: ``relight`` (the dataset model, its bake, the relight kernel and the light kinds),
``compress`` (the low-rank store), ``generate`` (datasets rendered from a scene),
``composite`` (a relit object over a background plate).
"""
