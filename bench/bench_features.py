"""Feature extraction's ORB pass, today's (one `detectAndCompute` over the image pyramid, the
grid spread keeping the rows of the keypoints it keeps: service/tracking/features.py) against the
code before it (`detect`, the spread, then `compute` on the kept keypoints: the pyramid built
twice), in one process on the same images.

    python bench/bench_features.py [--sequence rgbd_dataset_freiburg1_desk] [--frames 200]

Prints ms per frame of each (minimum and median of `--repeats` alternations), their ratios, and
whether the two give the same keypoints and descriptors bit for bit (exit status 1 if not).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_matching import sequence_extractor  # noqa: E402  (bench/, the script's folder)

from mnemoslam.service.tracking.features import FeatureExtractor, _keypoint_arrays  # noqa: E402


def two_passes(extractor: FeatureExtractor, grey: np.ndarray):
    """The code before: detect, spread the cv2.KeyPoints, compute the kept ones' descriptors."""
    kps = extractor._orb.detect(grey, None)
    if len(kps) < extractor.max_features // 2:
        kps = extractor._orb_low.detect(grey, None)
    xy, response, _ = _keypoint_arrays(kps)
    kps = [kps[i] for i in extractor._spread(xy, response, grey.shape)]
    kps, desc = extractor._orb.compute(grey, kps)
    xy, _, octave = _keypoint_arrays(kps)
    return desc, xy.astype(np.float32), octave


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="rgbd_dataset_freiburg1_desk", help="folder in MNEMOSLAM_DATA")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=9, help="alternations of the two (the machine's noise is ±10 %%)")
    args = ap.parse_args()
    ds, extractor = sequence_extractor(args.sequence, args.frames)
    greys = [ds.frame(i).grey for i in range(len(ds))]
    same = all(all(np.array_equal(a, b) for a, b in zip(extractor._detect(g), two_passes(extractor, g)))
               for g in greys)
    ms: dict[str, list[float]] = {"today": [], "before": []}
    for _ in range(args.repeats):  # alternated
        for name, fn in (("today", extractor._detect), ("before", lambda g: two_passes(extractor, g))):
            t0 = time.perf_counter()
            for g in greys:
                fn(g)
            ms[name].append((time.perf_counter() - t0) / len(greys) * 1e3)
    one, two = (np.array(ms[k]) for k in ("today", "before"))
    print(f"{len(greys)} frames of {args.sequence}, {args.repeats} alternations, ms per frame: one pass "
          f"min {one.min():.2f} median {np.median(one):.2f}, two passes min {two.min():.2f} median "
          f"{np.median(two):.2f} (ratio of minima {two.min() / one.min():.2f}, of medians "
          f"{np.median(two) / np.median(one):.2f}); same keypoints and descriptors: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
