"""The ibr-service rendering engine.

Pure arrays in, arrays out. Shared by every worker type. Never imports ``api_schemas``,
``service`` or ``workers`` and never reads the environment.

Importing ``engine`` (or its numba-free modules: ``errors``, ``metrics``, ``methods``) is cheap and
has no side effects, so the API process can use them. Modules with compiled kernels import
``engine._numba_setup`` first, which configures numba once per process.

Layout: the shared core (``scene``, ``camera``, ``raycast``, ``lights``, ``rng``, ``sched``,
``memory``, ``geometry/``, the ``reference`` renderer, ``imageio``, ``metrics``) and one subpackage
per technique: ``newviews`` (layered depth cube, light field, image-based ray tracing),
``relighting`` (illumination datasets) and ``walkthrough`` (animated scenes from range images).
"""

# Part of every artifact key (bakes, renders, relights): bump it when the same request would
# now produce different bytes, so caches never serve an older engine's answer.
# 0.2.0: LDC renders (silhouette rays, the refinement's mesh walk) and relights (float32 kernel).
# 0.2.1: LDC renders (silhouette pixels: the mesh test before the image-based ray) and relights
# (float32 point-light geometry with a float64 re-test of borderline rows).
# 0.3.0: reference renders, LLF bakes and datasets (the reference's samples come from the
# Owen-scrambled Sobol sampler, engine/sampler.py; camera samples unbiased at every spp).
# 0.4.0: reference renders and everything baked from them (rect lights are seen by camera rays and
# by mirror / glossy rays at chain hits and path vertices: caustic paths, visible lights).
# 0.5.0: reference renders and everything baked from them (glossy lobes weigh light sampling and
# their own rays by multiple importance sampling; Russian roulette on paths past 3 bounces).
# 0.6.0: LDC bakes and the LDC views' highlights (a rect light's points per LDC sample or shaded
# point are its own Owen-scrambled Sobol sequence over the light, engine/sampler.py).
# 0.7.0: LDC bakes and walkthrough bases (the indirect pass sizes each sample side's estimate from a
# pilot and traces it on fresh paths) and reference renders and LLF bakes with more indirect paths
# than camera samples (the hits of a first glossy bounce's rays share one hit's paths).
# 0.8.0: progressive reference renders (max_error / max_ms): the error is estimated and the samples
# planned over the pixels errors are measured on (engine/error_region.py), not the whole image.
# 0.9.0: LDC renders (a pixel's diffuse radiance is interpolated between the LDC's samples on its
# surface, not the nearest sample's).
# 0.10.0: progressive reference renders (the error region counts the pixels a rect light's
# corner covers, not only those whose centre ray sees it).
# 0.11.0: progressive reference renders of scenes with mirrors and emitters (the error region
# leaves out the pixels around an emitter seen in a mirror).
# 0.12.0: LDC bakes and walkthrough bases (their indirect pass traces one path count per sample side
# or base pixel, sized from the noise level, instead of a pilot-sized count per side).
# 0.13.0: LDC bakes and walkthrough bases of scenes with caustics (rect lights and mirror / glossy
# surfaces): a caustic photon map brings the light the paths found through mirror / glossy lobes.
# LDC views: the glossy lobe's reflection of the rect lights is shaded with the highlights.
# 0.14.0: path-traced walkthrough frames (each frame traces the paths its pilot says its noise
# target needs, instead of one count from a rule); walkthrough calibrations measured before it.
# 0.15.0: LDC views with ldc+ibrt:k (traced mirror rays show the rect lights they meet; the glossy lobe
# can be traced, view.glossy_rays).
# 0.16.0: reference renders with indirect paths of scenes with caustics seen on diffuse surfaces:
# the light reaching them through mirror / glossy lobes is light-traced (ReferenceParams.light_paths).
ENGINE_VERSION = "0.16.0"

# The last ENGINE_VERSION that changed what the reference renderer draws: benchmarks key the ground
# truths they cache on it, so a change elsewhere in the engine does not throw them away. (0.10.0
# and 0.11.0 change the error region, which moves an adaptive render's samples between a few
# pixels near emitters; the cached ground truths stay as converged, so they kept 0.8.0. 0.16.0's
# light tracing keeps the converged image and lowers the noise of scenes with caustics.)
REFERENCE_VERSION = "0.16.0"
