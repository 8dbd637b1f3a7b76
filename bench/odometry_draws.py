"""Odometry alone on one sequence over several RANSAC draws: ATE, RPE over 1 and 30 frames and
tracking frames/s per draw (issue 26's protocol: a single run's ATE is chaotic on fr1/desk).

    python bench/odometry_draws.py [--sequence rgbd_dataset_freiburg1_desk] [--draws 190,200,230]
                                   [--set KEY=VALUE ...] [--variant NAME:KEY=VALUE,KEY=VALUE ...]
                                   [--rounds N]

Features are extracted once (the first draw's config) and every draw tracks the same features
with `odometry.pnp_iterations` set to the draw, the tracker alone (as `mnemoslam run` with
`loop.enabled: false`). Frames/s is the tracker's alone (no decoding, no extraction).

With `--variant` (repeatable) the configuration given by `--set` ("base") and each variant (its
settings on top of it) run alternated in this one process, every draw of each, `--rounds`
times over; the summary gives each one's mean ATE and its best frames/s per draw as a ratio to
the base's (the machine's load moves a single run's frames/s by ±15 %).
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
    ap.add_argument("--variant", action="append", metavar="NAME:KEY=VALUE,...",
                    help="settings run alternated with the base configuration (repeatable)")
    ap.add_argument("--rounds", type=int, default=1, help="times every draw of every variant runs")
    args = ap.parse_args()
    variants = [("base", {})] + [_variant(v) for v in args.variant or []]
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
    ate: dict[str, dict[int, float]] = {name: {} for name, _ in variants}
    rpe30: dict[str, dict[int, float]] = {name: {} for name, _ in variants}
    fps: dict[str, dict[int, float]] = {name: {} for name, _ in variants}
    for _round in range(args.rounds):
        for draw in (int(x) for x in args.draws.split(",")):
            for name, extra in variants:
                cfg = load_config(overrides=merge_overrides(merge_overrides(overrides, extra),
                                                            {"odometry": {"pnp_iterations": draw}}))
                odometry = Odometry(ds.calibration.camera, cfg.odometry, seed=cfg.seed)
                stamps, poses = [], []
                t = time.perf_counter()
                for stamp, depth_stamp, features in frames:
                    r = odometry.track(features, stamp, depth_stamp)
                    if r.pose is not None:
                        stamps.append(stamp)
                        poses.append(r.pose)
                rate = len(frames) / (time.perf_counter() - t)
                est = Trajectory(np.array(stamps), np.array(poses))
                e1, e30 = evaluate(ds.ground_truth, est), evaluate(ds.ground_truth, est, rpe_delta=30)
                ate[name][draw], rpe30[name][draw] = e1.ate_rmse, e30.rpe_trans_rmse
                fps[name][draw] = max(fps[name].get(draw, 0.0), rate)
                label = f"{name}, " if len(variants) > 1 else ""
                print(f"{label}draw {draw}: ATE {e1.ate_rmse * 100:.2f} cm, "
                      f"RPE 1 frame {e1.rpe_trans_rmse * 100:.2f} cm {e1.rpe_rot_rmse:.2f} deg, "
                      f"RPE 30 frames {e30.rpe_trans_rmse * 100:.2f} cm, "
                      f"lost {len(frames) - len(stamps)}, tracking {rate:.1f} frames/s", flush=True)
    for name, _ in variants:
        line = (f"mean of {len(ate[name])} draws: ATE {np.mean(list(ate[name].values())) * 100:.2f} cm, "
                f"RPE 30 frames {np.mean(list(rpe30[name].values())) * 100:.2f} cm")
        if len(variants) > 1:
            ratio = np.mean([fps[name][d] / fps["base"][d] for d in fps[name]])
            line = f"{name}: {line}, tracking frames/s {ratio:.2f}x the base's (best of {args.rounds} per draw)"
        print(line)
    return 0


def _variant(text: str) -> tuple[str, dict]:
    """NAME:KEY=VALUE,KEY=VALUE as (NAME, overrides)."""
    name, _, sets = text.partition(":")
    if not name or not sets:
        raise SystemExit(f"--variant {text!r}: expected NAME:KEY=VALUE[,KEY=VALUE...]")
    return name, parse_sets(sets.split(","))


if __name__ == "__main__":
    sys.exit(main())
