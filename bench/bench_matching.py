"""Tracking's descriptor search, today's (FAISS exact binary k-NN, service/tracking/matching.py)
against OpenCV's batchDistance (the code before it), in one process on the same descriptors.

    python bench/bench_matching.py [--sequence rgbd_dataset_freiburg1_desk] [--frames 120]

Real descriptors: each frame's ORB features of a TUM sequence against the previous 3,000 map-like
descriptors (the tracker's `odometry.local_map_size`). Prints ms per search of each, the ratio,
and whether the two give the same nearest index (where it is unique) and the same two distances.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.service.config import load_config  # noqa: E402
from mnemoslam.service.tracking.features import FeatureExtractor  # noqa: E402
from mnemoslam.service.tracking.matching import two_nearest  # noqa: E402


def opencv_two_nearest(query: np.ndarray, train: np.ndarray):
    dist, nearest = cv2.batchDistance(query, train, -1, normType=cv2.NORM_HAMMING, K=2, update=0, crosscheck=False)
    return nearest[:, 0].astype(int), dist[:, 0].astype(np.float64), dist[:, 1].astype(np.float64)


def sequence_extractor(sequence: str, frames: int):
    """The first `frames` of a sequence in MNEMOSLAM_DATA and the default feature extractor for
    it, OpenCV on one thread (the benches time one core): (dataset, extractor)."""
    cv2.setNumThreads(1)
    data = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data"))
    ds = open_dataset(data / sequence, max_frames=frames)
    cfg = load_config()
    return ds, FeatureExtractor(ds.calibration, cfg.features, cfg.stereo)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="rgbd_dataset_freiburg1_desk", help="folder in MNEMOSLAM_DATA")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--map-size", type=int, default=3000)
    args = ap.parse_args()
    ds, extractor = sequence_extractor(args.sequence, args.frames)
    descs = [extractor.extract(ds.frame(i)).descriptors for i in range(len(ds))]
    pairs = []
    for i in range(1, len(descs)):
        train = np.concatenate(descs[max(0, i - 6):i])[-args.map_size:]
        pairs.append((descs[i], train))
    print(f"{len(pairs)} searches, {np.mean([len(q) for q, _ in pairs]):.0f} queries x "
          f"{np.mean([len(t) for _, t in pairs]):.0f} descriptors on average")
    same = True
    for q, t in pairs:
        a, b = two_nearest(q, t), opencv_two_nearest(q, t)
        unique = a[1] < a[2]
        same &= bool(np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])
                     and np.array_equal(a[0][unique], b[0][unique]))
    best = {}
    for _ in range(3):  # alternated, best of three
        for name, fn in (("opencv batchDistance", opencv_two_nearest), ("faiss IndexBinaryFlat", two_nearest)):
            t0 = time.perf_counter()
            for q, t in pairs:
                fn(q, t)
            best[name] = min(best.get(name, np.inf), (time.perf_counter() - t0) / len(pairs) * 1000)
    for name, ms in best.items():
        print(f"{name:24s} {ms:7.2f} ms per search")
    print(f"ratio faiss / opencv: {best['faiss IndexBinaryFlat'] / best['opencv batchDistance']:.2f}; "
          f"same nearest and distances: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
