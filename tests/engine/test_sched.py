"""engine.sched: the shared block counter of the parallel kernels (dynamic scheduling)."""

import numba as nb
import numpy as np
import pytest

from engine.sched import next_block


@nb.njit(parallel=True, cache=False)
def _take_all(n_blocks, n_threads, spin):
    counter = np.zeros(1, np.int64)
    taken = np.zeros(n_blocks, np.int64)
    owner = np.full(n_blocks, -1, np.int64)
    for t in nb.prange(n_threads):
        while True:
            b = next_block(counter)
            if b >= n_blocks:
                break
            taken[b] += 1
            owner[b] = t
            x = 0.0
            for j in range(spin):  # some work per block, so the threads overlap
                x += np.sqrt(j + b)
            if x < 0.0:
                taken[b] += 1
    return taken, owner, counter


@nb.njit(cache=False)
def _serial(k):
    c = np.zeros(1, np.int64)
    out = np.empty(k, np.int64)
    for i in range(k):
        out[i] = next_block(c)
    return out, c[0]


def test_serial_counter_counts_up():
    out, last = _serial(5)
    assert out.tolist() == [0, 1, 2, 3, 4]
    assert last == 5


@pytest.mark.parametrize("n_threads", [1, 2, 7])
def test_every_block_is_taken_exactly_once(n_threads):
    prev = nb.get_num_threads()
    nb.set_num_threads(min(n_threads, nb.config.NUMBA_NUM_THREADS))
    try:
        taken, owner, counter = _take_all(20_000, n_threads, 50)
    finally:
        nb.set_num_threads(prev)
    assert taken.min() == 1 and taken.max() == 1
    assert owner.min() >= 0 and owner.max() < n_threads
    # every thread's last fetch overshoots by one: the counter ends at n_blocks + n_threads
    assert int(counter[0]) == 20_000 + n_threads
