"""The voxel map's key hash against a Python dict: batches with repeats, tombstones, rebuilds."""
from __future__ import annotations

import numpy as np
import pytest

from mdr_slam.fusion.hash_map import KEY_LIMIT, KeyHash, pack_keys


def _check(h, ref, keys):
    got = h.find(keys)
    want = np.array([ref.get(int(k), -1) for k in keys], np.int64)
    assert np.array_equal(got, want)
    assert len(h) == len(ref)
    # the counts that decide the rebuilds are the table's
    assert h._live == (h._keys >= 0).sum() and h._tombs == (h._keys == -2).sum()


def test_pack_keys_is_one_to_one_within_the_limit():
    rng = np.random.default_rng(0)
    k = np.concatenate([rng.integers(-KEY_LIMIT, KEY_LIMIT, (5000, 3)), rng.integers(0, 6, (5000, 1))], 1)
    k = np.concatenate([k, [[-KEY_LIMIT, -KEY_LIMIT, -KEY_LIMIT, 0], [KEY_LIMIT - 1] * 3 + [7]]])
    p = pack_keys(k)
    assert (p >= 0).all()
    assert len(np.unique(p)) == len(np.unique(k, axis=0))
    # neighbours along each axis and bin differ
    base = np.array([[3, -4, 5, 2]])
    for d in np.eye(4, dtype=np.int64):
        assert pack_keys(base)[0] != pack_keys(base + d)[0]


def test_random_batches_agree_with_a_dict():
    rng = np.random.default_rng(1)
    h, ref = KeyHash(16), {}
    universe = pack_keys(np.concatenate([rng.integers(-300, 300, (40000, 3)),
                                         rng.integers(0, 6, (40000, 1))], 1))
    next_value = 0
    for step in range(120):
        op = rng.random()
        batch = universe[rng.integers(0, len(universe), rng.integers(0, 3000))]
        if op < 0.55:
            vals = np.arange(next_value, next_value + len(batch))
            next_value += len(batch)
            ok = h.insert(batch, vals)
            want = np.zeros(len(batch), bool)
            for i, k in enumerate(batch.tolist()):
                if k not in ref:
                    ref[k] = int(vals[i])
                    want[i] = True
            assert np.array_equal(ok, want), step
        elif op < 0.8:
            n = h.erase(batch)
            gone = {k for k in batch.tolist() if k in ref}
            for k in gone:
                del ref[k]
            assert n == len(gone)
        _check(h, ref, universe[rng.integers(0, len(universe), 2000)])
    k, v = h.items()
    assert dict(zip(k.tolist(), v.tolist())) == ref
    assert h._live + h._tombs <= 0.5 * h.capacity()


def test_erase_and_reinsert_reuses_tombstones_without_growing():
    h = KeyHash(1 << 12)
    keys = np.arange(1000, dtype=np.int64) * 7919
    assert h.insert(keys, np.arange(1000)).all()
    cap = h.capacity()
    for r in range(50):                 # churn: tombstones are taken again or rebuilt away
        assert h.erase(keys[r::50]) == len(keys[r::50])
        assert (h.find(keys[r::50]) == -1).all()
        assert h.insert(keys[r::50], np.arange(len(keys[r::50])) + 10 * r).all()
    assert h.capacity() == cap and len(h) == 1000
    assert (h.find(keys) >= 0).all()
    assert (h.find(keys + 1) == -1).all()


@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_single_batches(n):
    h = KeyHash()
    keys = np.arange(n, dtype=np.int64)
    assert h.insert(keys, keys).sum() == n
    assert h.find(np.zeros(0, np.int64)).shape == (0,)
    assert h.erase(np.zeros(0, np.int64)) == 0
    assert np.array_equal(h.find(keys), keys)
