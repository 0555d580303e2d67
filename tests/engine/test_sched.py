"""engine.sched: the shared block counter of the parallel kernels (dynamic scheduling)."""

import numba as nb
import numpy as np
import pytest

from engine.sched import next_block, run_on_threads, run_pieces_parallel, threads_for


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


def test_pieces_cover_the_range_once_and_get_the_extra_arguments():
    seen = np.zeros(10_000, np.int64)

    def piece(lo, hi, out, step):
        out[lo:hi] += step

    run_pieces_parallel(piece, seen.size, 100, False, seen, 1)
    assert np.all(seen == 1)


def test_a_pool_thread_runs_nested_calls_in_itself_instead_of_waiting_on_the_pool():
    """A kernel piece that itself asks for every thread (serial=False) gets one: waiting on the
    pool it runs in could deadlock."""
    asked: list[int] = []

    def piece(lo, hi):
        asked.append(threads_for(False))
        run_on_threads(lambda: None, serial=False)  # returns instead of waiting on the busy pool

    run_pieces_parallel(piece, 8, 1, False)
    if nb.get_num_threads() > 1:
        assert asked and set(asked) == {1}
