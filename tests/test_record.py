"""The env's store of recorded samples (blf_gym.envs.envcore._Record) against a plain list of per-arm
copies: slabs with full and partial counts, arms restarting at different steps, releases, and the
store running out of slabs (dropping what no episode reads, or growing)."""

import numpy as np
import pytest

from blf_gym.envs.envcore import _Record
from blf_gym.kernel.simulate import N_CHANNELS


@pytest.mark.parametrize("seed", range(6))
def test_record_keeps_each_arms_episode_as_per_arm_copies_would(seed):
    rng = np.random.default_rng(seed)
    N, m, n = int(rng.integers(1, 5)), int(rng.integers(1, 4)), 3
    store = _Record(N, m, n, steps=int(rng.integers(1, 6)))
    naive = [[] for _ in range(N)]  # what each arm's episode holds so far
    stopped = np.zeros(N, dtype=bool)
    for _ in range(60):
        restart = [i for i in range(N) if rng.random() < 0.1]
        store.restart(restart)
        for i in restart:
            naive[i], stopped[i] = [], False
        slab = store.slab()
        assert slab.shape == (N, m, N_CHANNELS, n) and slab.flags.c_contiguous
        nrec = np.zeros(N, dtype=np.int64)
        for i in range(N):
            # an arm writes all m samples until it stops; its last step may be partial, then nothing
            k = 0 if stopped[i] else (m if rng.random() < 0.9 else int(rng.integers(0, m)))
            stopped[i] |= k < m
            nrec[i] = k
            slab[i, :k] = rng.standard_normal((k, N_CHANNELS, n))
            slab[i, k:] = np.nan  # what the kernel leaves unwritten is never read
            naive[i].append(slab[i, :k].copy())
        store.commit(nrec)
        for i in range(N):
            if rng.random() < 0.05:
                release = bool(rng.random() < 0.5)
                got = store.samples(i, release=release)
                want = np.concatenate(naive[i]) if naive[i] else np.zeros((0, N_CHANNELS, n))
                np.testing.assert_array_equal(got, want)
                if release:  # forgotten; the arm's later steps are kept
                    naive[i] = []
    for i in range(N):
        want = np.concatenate(naive[i]) if naive[i] else np.zeros((0, N_CHANNELS, n))
        np.testing.assert_array_equal(store.samples(i, release=True), want)
    assert store.buf.shape[0] == 0  # every arm released: nothing is kept


def test_record_drops_slabs_no_episode_reads_instead_of_growing():
    store = _Record(2, 1, 3, steps=4)
    for step in range(40):
        if step % 4 == 0:
            store.restart([0, 1])  # both arms start an episode every 4 steps
        store.slab()[:] = step
        store.commit(np.ones(2, dtype=np.int64))
    assert store.buf.shape[0] == 4  # never grew: the finished episodes' slabs were reused
    np.testing.assert_array_equal(store.samples(1)[:, 0, 0], [36, 37, 38, 39])
