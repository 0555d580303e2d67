"""How much memory a render job will need, estimated from its request before it is queued.

The API refuses a render whose estimate exceeds ``Settings.max_render_bytes`` (422 naming the
estimate and the limit), instead of letting a render worker swell until the machine swaps.

The numbers are the growth of a warm render worker's peak RSS while it runs the real render job
(render, encode every output, publish; ``tests/workers/queue/render_rss.py``), measured on this
project's 2-core machine on the warm-up scene (point, directional and rect lights; glossy, mirror
and emissive materials):

- ``reference``: image-sized buffers (float64 radiance accumulator, normals, depth, ids, the copies
  the encoders write): 235 bytes per pixel (512 x 512 -> 1024 x 1024 at 4 spp). The wavefront
  chunk (at most ``REFERENCE_CHUNK_PIXELS`` pixels, two pipelines in flight) holds every sample's
  rays: per chunk pixel and sample 928 bytes, plus 438 per glossy sample and 135 per area-light
  sample beyond the first (512 x 512, spp 4 / 16, glossy 1 / 8, area 1 / 16: 106 MiB to 656 MiB).
  A render at 1 spp needs about what 2 spp predict, so the estimate counts at least 2. Indirect
  samples are counted like glossy ones (not measured).
- the LDC methods render the whole view at once (warp, candidate lists, provenance): ``ldc+llf``
  grew 74-90 bytes per pixel (1024 x 1024, 2048 x 2048); ``LDC_BYTES_PER_PIXEL`` allows about
  twice that for ``ldc+ibrt:k``'s retracing (not measured separately).

Each estimate is then multiplied by ``MARGIN``: it is a refusal threshold, not an accounting.
"""

from __future__ import annotations

from api_schemas.service import RenderRequest, method_needs_bake

__all__ = [
    "FIXED_BYTES",
    "LDC_BYTES_PER_PIXEL",
    "MARGIN",
    "REFERENCE_BYTES_PER_PIXEL",
    "REFERENCE_BYTES_PER_AREA_RAY",
    "REFERENCE_BYTES_PER_CHUNK_SAMPLE",
    "REFERENCE_BYTES_PER_GLOSSY_RAY",
    "REFERENCE_CHUNK_PIXELS",
    "estimate_render_bytes",
]

REFERENCE_BYTES_PER_PIXEL = 240
REFERENCE_BYTES_PER_CHUNK_SAMPLE = 930
REFERENCE_BYTES_PER_GLOSSY_RAY = 440
REFERENCE_BYTES_PER_AREA_RAY = 135
REFERENCE_CHUNK_PIXELS = 16384
"""``engine.reference.ReferenceParams.chunk_pixels``: pixels per wavefront chunk."""
LDC_BYTES_PER_PIXEL = 180
FIXED_BYTES = 32 << 20
"""Per-job overhead that does not scale with the image (scene, kernels' scratch, encoder state)."""
MARGIN = 1.25


def estimate_render_bytes(req: RenderRequest, width: int, height: int) -> int:
    """Estimated growth of a render worker's peak memory while it runs ``req`` at ``width`` x
    ``height`` (the request's camera, or the scene's)."""
    pixels = width * height
    if method_needs_bake(req.method):
        body = LDC_BYTES_PER_PIXEL * pixels
    else:
        p = req.params
        chunk = min(pixels, REFERENCE_CHUNK_PIXELS)
        per_sample = (REFERENCE_BYTES_PER_CHUNK_SAMPLE
                      + REFERENCE_BYTES_PER_GLOSSY_RAY * (p.glossy_samples - 1 + p.indirect_samples)
                      + REFERENCE_BYTES_PER_AREA_RAY * (p.area_light_samples - 1))
        body = REFERENCE_BYTES_PER_PIXEL * pixels + chunk * max(p.spp, 2) * per_sample
    return int(MARGIN * (body + FIXED_BYTES))
