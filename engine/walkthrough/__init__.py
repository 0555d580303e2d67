"""Image-based walkthroughs of animated scenes with global illumination (docs/algorithms.md part C).

See docs/walkthrough.md. Modules: ``range_images`` (cube-map base images), ``viewspace``,
``decompose`` (base viewpoints and time samples), ``reconstruct`` (reprojection and fill),
``bake`` (WalkthroughBake, WalkthroughRenderer, quality presets), ``ground_truth`` (converged
and path-traced frames), ``path_settings`` (how a path-traced frame samples), ``quality`` (the
walkthrough quality contracts' model and planner).
"""
