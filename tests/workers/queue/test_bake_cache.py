"""The render worker's LRU holds LDC view renderers per bake next to reference renderers, in one
byte budget; an entry that grows in place (the IBRT structure is built on first use) is re-sized."""

from __future__ import annotations

from api_schemas.scene import Scene
from tests.workers.queue.jobs_for_tests import tiny_scene
from workers.cache import CachedBakeRenderer, LRUBytesCache, RendererCache, runtime_scene_bytes


def test_resize_updates_the_total_and_evicts_when_over_budget() -> None:
    c: LRUBytesCache[str] = LRUBytesCache(100)
    c.put("a", "A", 30)
    c.put("b", "B", 30)
    c.resize("a", 50)
    assert c.total_bytes == 80 and c.keys() == ["b", "a"]  # resizing counts as a use
    c.resize("b", 60)  # 110 > 100: the least recently used other entry goes
    assert c.keys() == ["b"] and c.total_bytes == 60 and c.evictions == 1
    c.resize("missing", 10)  # no entry: nothing happens
    assert c.keys() == ["b"]


def test_bake_renderers_share_the_budget_with_reference_renderers() -> None:
    from engine.newviews.effects import analyze
    from engine.newviews.ldc import bake_ldc
    from engine.newviews.renderer import LDCViewRenderer
    from engine.raycast import make_caster
    from workers.scene_loader import load_scene

    def loader(scene: Scene) -> CachedBakeRenderer:
        loaded = load_scene(scene, lambda p: (b"", ""))
        plan = analyze(loaded.runtime)
        ldc = bake_ldc(loaded.runtime, make_caster(loaded.runtime, "embree"), 16, plan=plan, max_layers=4,
                       area_light_samples=1)
        return CachedBakeRenderer(loaded, LDCViewRenderer(loaded.runtime, ldc, None, plan), "k", {})

    first = loader(tiny_scene())
    size = runtime_scene_bytes(first.loaded.runtime) + first.renderer.nbytes
    cache = RendererCache(int(size * 1.5))
    entry, hit = cache.get_or_load_bake("one", lambda: first)
    assert entry is first and not hit and cache.total_bytes == size
    again, hit = cache.get_or_load_bake("one", lambda: loader(tiny_scene()))
    assert again is first and hit
    cache.get_or_load_bake("two", lambda: loader(tiny_scene(intensity=4.0)))
    assert cache.keys() == ["bake:two"]  # two bakes do not fit: the older one went
