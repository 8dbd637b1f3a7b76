"""Descriptor matching shared by tracking (frame against the local map) and mapping (loop,
proximity and path verification, link refinement): binary descriptors, Hamming distance."""
from __future__ import annotations

import faiss
import numpy as np

# FAISS's exact binary k-NN (popcount over 64-bit words, blocked): ~4.5x OpenCV's batchDistance
# (1,000 frame features against 3,000 map points, one core: bench/bench_matching.py), and it
# releases the GIL as OpenCV does. One thread: a tracker per robot, the map update and the
# semantic worker already share the cores; OpenMP's spinning threads would take them.


def two_nearest(query: np.ndarray, train: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact nearest and second-nearest train descriptor of each query (uint8 rows, Hamming):
    (index of the nearest, its distance, the second distance). Among train descriptors at the
    same smallest distance the index is any of them (then the two distances are equal)."""
    # OpenMP's thread count is each calling thread's own setting (a tracker's thread would get
    # one OpenMP thread per core): set it for this thread, every call (it costs nothing)
    faiss.omp_set_num_threads(1)
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
    # One query per train point: keep the closest.
    ti, qi = one_per_query(ti[ok], qi[ok], d1[ok])
    return qi, ti


def match_map_points(query: np.ndarray, train: np.ndarray, ratio: float, max_dist: int):
    """Nearest-neighbour matching the other way round, as ORB-SLAM's search by projection:
    each train point (a map point) takes its nearest query (a keypoint) under the ratio test
    against its second nearest query; duplicates of one surface point in the map (points of
    several passes over it) all find that keypoint, where a ratio test among map points would
    refuse it. Returns (query indices, train indices, distances), several train points per query
    possible (`one_per_query`)."""
    if len(query) < 2 or len(train) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    qi, d1, d2 = two_nearest(train, query)
    ti = np.arange(len(train))
    ok = (d1 <= max_dist) & (d1 < ratio * d2)
    return qi[ok], ti[ok], d1[ok]


def match_map_points_tiled(query: np.ndarray, query_xy: np.ndarray, train: np.ndarray, train_uv: np.ndarray,
                           radius: float, ratio: float, max_dist: int, tile: float = 160.0):
    """`match_map_points` by projection: the image is cut into `tile`-pixel squares and the map
    points projecting into one are compared only with the keypoints within `radius` of the
    square (the nearest and second nearest among those), so a frame costs about the tiles'
    share of the distances (~1/8 with 160-px tiles on a VGA image) instead of all of them.
    Returns (query indices, train indices, distances) as `match_map_points`."""
    out_q, out_t, out_d = [np.zeros(0, int)], [np.zeros(0, int)], [np.zeros(0)]
    if len(train) == 0 or len(query) < 2:
        return out_q[0], out_t[0], out_d[0]
    cell = np.floor(train_uv / tile).astype(np.int64)
    key = cell[:, 1] * 100003 + cell[:, 0]
    order = np.argsort(key, kind="stable")
    bounds = np.nonzero(np.r_[True, key[order][1:] != key[order][:-1], True])[0]
    for a, b in zip(bounds[:-1], bounds[1:]):
        t = order[a:b]
        cx, cy = cell[t[0]] * tile
        q = np.nonzero((query_xy[:, 0] >= cx - radius) & (query_xy[:, 0] < cx + tile + radius)
                       & (query_xy[:, 1] >= cy - radius) & (query_xy[:, 1] < cy + tile + radius))[0]
        if not len(q):
            continue
        if len(q) == 1:  # one keypoint there: no second nearest, the ratio test passes
            d = np.bitwise_count(train[t] ^ query[q[0]]).sum(axis=1, dtype=np.int32)
            ok = d <= max_dist
            out_q.append(np.full(int(ok.sum()), q[0]))
            out_t.append(t[ok])
            out_d.append(d[ok].astype(np.float64))
            continue
        nearest, d1, d2 = two_nearest(train[t], query[q])
        ok = (d1 <= max_dist) & (d1 < ratio * d2)
        out_q.append(q[nearest[ok]])
        out_t.append(t[ok])
        out_d.append(d1[ok])
    return np.concatenate(out_q), np.concatenate(out_t), np.concatenate(out_d)


def one_per_query(qi: np.ndarray, ti: np.ndarray, dist: np.ndarray, prefer: np.ndarray | None = None):
    """Of several train points matched to one query keep the one with the lowest `prefer` (e.g.
    the oldest map point), the closest among equals (or the closest when `prefer` is None).
    Returns (query indices, train indices) in train order."""
    key = dist if prefer is None else prefer
    o = np.lexsort((dist, key, qi))
    first = np.ones(len(o), bool)
    first[1:] = qi[o][1:] != qi[o][:-1]
    keep = np.sort(o[first])
    return qi[keep], ti[keep]
