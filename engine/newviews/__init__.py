"""New views of non-diffuse scenes: a layered depth cube (LDC) with a layered light field (LLF),
rendered by 3D warping and image-based ray tracing (docs/ldc.md).

Modules, in the order a bake and a render use them: ``effects`` (which effects a scene calls for:
what is baked and which passes run), ``ldi`` (layered depth images), ``ldc`` (the cube's bake and
per-sample shading), ``llf`` (the light field's bake), ``warp`` (3D warp of the cube into a view,
with hole detection), ``ibrt`` (image-based ray tracing through the cube), ``view_pass``
(highlights and light-field gathers per pixel), ``renderer`` (``LDCViewRenderer``: the stages
in order, with provenance and timings per stage).
"""
