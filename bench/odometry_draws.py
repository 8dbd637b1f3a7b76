"""Odometry alone on one sequence over several RANSAC draws: ATE, RPE over 1 and 30 frames and
tracking frames/s per draw (issue 26's protocol: a single run's ATE is chaotic on fr1/desk).

    python bench/odometry_draws.py [--sequence rgbd_dataset_freiburg1_desk] [--draws 190,200,230]
                                   [--set KEY=VALUE ...]

Features are extracted once (the first draw's config) and every draw tracks the same features
with `odometry.pnp_iterations` set to the draw, the tracker alone (as `mnemoslam run` with
`loop.enabled: false`). Frames/s is the tracker's alone (no decoding, no extraction).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.client.kernel.trajectory import Trajectory  # noqa: E402
from mnemoslam.service.config import load_config, merge_overrides, parse_sets  # noqa: E402
from mnemoslam.service.evaluation import evaluate  # noqa: E402
from mnemoslam.service.tracking.features import FeatureExtractor  # noqa: E402
from mnemoslam.service.tracking.odometry import Odometry  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="rgbd_dataset_freiburg1_desk", help="folder in MNEMOSLAM_DATA")
    ap.add_argument("--draws", default="190,200,230", help="odometry.pnp_iterations values, comma-separated")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override (repeatable)")
    args = ap.parse_args()
    data = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data"))
    ds = open_dataset(data / args.sequence)
    if ds.ground_truth is None:
        print(f"{args.sequence}: no ground truth", file=sys.stderr)
        return 1
    overrides = parse_sets(args.set)
    config = load_config(overrides=overrides)
    extractor = FeatureExtractor(ds.calibration, config.features, config.stereo)
    frames = []
    for i in range(len(ds)):
        f = ds.frame(i)
        frames.append((f.stamp, f.extras.get("depth_stamp"), extractor.extract(f)))
    ate, rpe30 = [], []
    for draw in (int(x) for x in args.draws.split(",")):
        cfg = load_config(overrides=merge_overrides(overrides, {"odometry": {"pnp_iterations": draw}}))
        odometry = Odometry(ds.calibration.camera, cfg.odometry, seed=cfg.seed)
        stamps, poses = [], []
        t = time.perf_counter()
        for stamp, depth_stamp, features in frames:
            r = odometry.track(features, stamp, depth_stamp)
            if r.pose is not None:
                stamps.append(stamp)
                poses.append(r.pose)
        fps = len(frames) / (time.perf_counter() - t)
        est = Trajectory(np.array(stamps), np.array(poses))
        e1, e30 = evaluate(ds.ground_truth, est), evaluate(ds.ground_truth, est, rpe_delta=30)
        ate.append(e1.ate_rmse)
        rpe30.append(e30.rpe_trans_rmse)
        print(f"draw {draw}: ATE {e1.ate_rmse * 100:.2f} cm, RPE 1 frame {e1.rpe_trans_rmse * 100:.2f} cm "
              f"{e1.rpe_rot_rmse:.2f} deg, RPE 30 frames {e30.rpe_trans_rmse * 100:.2f} cm, "
              f"lost {len(frames) - len(stamps)}, tracking {fps:.1f} frames/s", flush=True)
    print(f"mean of {len(ate)} draws: ATE {np.mean(ate) * 100:.2f} cm, RPE 30 frames {np.mean(rpe30) * 100:.2f} cm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
