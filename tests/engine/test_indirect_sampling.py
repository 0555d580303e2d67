"""The fixed sampler's path count per LDC sample side, and the bake cost estimate built on it."""
import pytest

from api_schemas.service import BakeParams
from engine.newviews.indirect import IndirectParams
from engine.newviews.indirect_sampling import expected_paths_per_side, fixed_paths
from producer.costs import expected_paths


@pytest.mark.parametrize(("noise", "paths"), [(0.02, 256), (0.014, 512), (0.03, 128), (0.01, 1024),
                                              (0.05, 64), (0.2, 64), (0.002, 1024)])
def test_the_count_is_the_power_of_two_nearest_the_rule_within_min_and_max(noise, paths):
    # (0.32 / noise)^2: 0.05 -> 41, nearest 32, raised to min_paths 64; 0.002 -> 25600, capped at 1024
    assert fixed_paths(noise, 64, 1024, 8) == paths


def test_the_count_is_whole_rounds_and_at_least_two_of_them():
    assert fixed_paths(0.02, 2, 1000, 8) == 256
    assert fixed_paths(0.001, 2, 1000, 8) == 1000  # the cap, rounded down to whole rounds of 8
    assert fixed_paths(0.001, 2, 1003, 8) == 1000
    assert fixed_paths(0.4, 2, 1024, 32) == 64  # two rounds of 32, the fewest whose spread is an error


def test_the_engine_traces_the_count_the_api_prices():
    for noise in (0.01, 0.02, 0.05):
        ip = IndirectParams(noise=noise)
        api = BakeParams(indirect={"noise": noise})
        assert ip.paths_per_side == expected_paths(api) == fixed_paths(noise, 64, 1024, 8)
        assert not ip.adaptive
    # stride 2 traces about a quarter of the sides
    assert expected_paths(BakeParams(indirect={"noise": 0.02, "stride": 2})) == 64.0
    # the adaptive sampler: its pilot and a share of the way to max_paths
    assert expected_paths(BakeParams(indirect={"sampling": "adaptive"})) == pytest.approx(64 + 0.2 * 960)
    assert IndirectParams(sampling="adaptive").adaptive
    assert not IndirectParams(sampling="adaptive", min_paths=64, max_paths=64).adaptive  # nothing to size


def test_unknown_samplers_and_noise_levels_are_refused():
    with pytest.raises(ValueError, match="sampling"):
        expected_paths_per_side("stratified", 0.02, 64, 1024, 8)
    with pytest.raises(ValueError, match="noise"):
        fixed_paths(0.0, 64, 1024, 8)
