"""Descriptor matching shared by tracking (frame against the local map) and mapping (loop,
proximity and path verification, link refinement): binary descriptors, Hamming distance."""
from __future__ import annotations

import faiss
import numpy as np

# FAISS's exact binary k-NN (popcount over 64-bit words, blocked): ~4.5x OpenCV's batchDistance
# (1,000 frame features against 3,000 map points, one core: bench/bench_matching.py), and it
# releases the GIL as OpenCV does. One thread: a tracker per robot, the map update and the
# semantic worker already share the cores; OpenMP's spinning threads would take them.
faiss.omp_set_num_threads(1)


def two_nearest(query: np.ndarray, train: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact nearest and second-nearest train descriptor of each query (uint8 rows, Hamming):
    (index of the nearest, its distance, the second distance). Among train descriptors at the
    same smallest distance the index is any of them (then the two distances are equal)."""
    index = faiss.IndexBinaryFlat(8 * train.shape[1])
    index.add(np.ascontiguousarray(train, np.uint8))
    dist, nearest = index.search(np.ascontiguousarray(query, np.uint8), 2)
    return nearest[:, 0].astype(int), dist[:, 0].astype(np.float64), dist[:, 1].astype(np.float64)


def match_descriptors(query: np.ndarray, train: np.ndarray, ratio: float, max_dist: int):
    """Nearest-neighbour matching with the ratio test and one match per train point.
    Returns (query indices, train indices)."""
    if len(train) < 2 or len(query) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    ti, d1, d2 = two_nearest(query, train)
    qi = np.arange(len(query))
    # (a tie at the smallest distance fails the ratio test whichever index the search kept)
    ok = (d1 <= max_dist) & (d1 < ratio * d2)
    qi, ti, d1 = qi[ok], ti[ok], d1[ok]
    # One query per train point: keep the closest.
    order = np.lexsort((d1, ti))
    first = np.ones(len(order), bool)
    first[1:] = ti[order][1:] != ti[order][:-1]
    keep = np.sort(order[first])
    return qi[keep], ti[keep]
