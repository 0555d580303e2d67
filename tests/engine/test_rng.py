import numpy as np
from scipy import stats

from engine.rng import stream_key, uniforms


def test_uniforms_are_uniform_and_independent():
    u = uniforms(stream_key(1, 2, 3), 20000, 3)
    assert u.min() >= 0.0 and u.max() < 1.0
    for j in range(3):
        assert stats.kstest(u[:, j], "uniform").pvalue > 1e-3
    c = np.corrcoef(u.T)
    assert np.all(np.abs(c - np.eye(3)) < 0.03)


def test_streams_are_deterministic_and_distinct():
    a = uniforms(stream_key(0, 1), 100, 2)
    assert np.array_equal(a, uniforms(stream_key(0, 1), 100, 2))
    assert not np.array_equal(a, uniforms(stream_key(0, 2), 100, 2))
    assert not np.array_equal(a, uniforms(stream_key(1, 1), 100, 2))
