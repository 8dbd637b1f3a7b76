"""Descriptor matching (service/tracking/matching.py): exact two nearest neighbours in Hamming
distance, the ratio test, one match per train descriptor."""
from __future__ import annotations

import numpy as np

from mnemoslam.service.tracking.matching import match_descriptors, two_nearest


def _flip(desc: np.ndarray, bits: np.ndarray) -> np.ndarray:
    """desc with the given bit positions (0..255) flipped."""
    out = np.unpackbits(desc.copy())
    out[bits] ^= 1
    return np.packbits(out)


def test_two_nearest_are_the_brute_force_ones():
    rng = np.random.default_rng(3)
    train = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    query = np.stack([_flip(train[i], rng.choice(256, k, replace=False)) for i, k in
                      zip(rng.choice(500, 60, replace=False), rng.integers(0, 40, 60))])
    brute = np.unpackbits(query[:, None, :] ^ train[None, :, :], axis=2).sum(axis=2)
    nearest, d1, d2 = two_nearest(query, train)
    order = np.sort(brute, axis=1)
    assert np.array_equal(d1, order[:, 0]) and np.array_equal(d2, order[:, 1])
    assert np.array_equal(brute[np.arange(len(query)), nearest], d1)


def test_ratio_test_and_one_query_per_train_point():
    rng = np.random.default_rng(5)
    train = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    q_good = _flip(train[7], np.arange(5))            # 5 bits from train 7: a match
    q_worse = _flip(train[7], np.arange(20, 30))      # also nearest to 7, farther: loses the train point
    q_far = _flip(train[9], np.arange(0, 256, 3)[:70])  # 70 bits away: beyond max_dist
    twin = train[11].copy()
    train[12] = _flip(twin, np.arange(4))             # 11 and 12 alike ...
    q_ambiguous = _flip(twin, np.arange(2, 4))        # ... and the query 2 bits from both: no match
    query = np.stack([q_worse, q_good, q_far, q_ambiguous])
    qi, ti = match_descriptors(query, train, ratio=0.8, max_dist=64)
    assert qi.tolist() == [1] and ti.tolist() == [7]
    # a tie at the smallest distance fails the ratio test whatever index the search kept
    tie = np.stack([train[20], train[20]])
    qi, ti = match_descriptors(train[20:21], tie, ratio=0.8, max_dist=64)
    assert len(qi) == 0
    # nothing to match against
    assert len(match_descriptors(query, train[:1], 0.8, 64)[0]) == 0
