"""Run every sequence in MNEMOSLAM_DATA and the synthetic scene through the offline
pipeline; print ATE RMSE, frames/s and peak memory per sequence as a table.

    python bench/run_sequences.py [--only NAME] [--synthetic-frames N] [--set KEY=VALUE ...]

Frames/s is end to end (file decoding + pipeline) in one process: "fps e2e" for tracking
alone (odometry + keyframes + memory, what the service's tracking thread does; its map update
runs in another process), "fps e2e+loops" with the map update (loop closure, graph) inline as
offline runs do it. "pipeline fps" excludes decoding (frames are decoded before the clock
starts). ATE is that of the run with loop closure ("ATE odom" without); "ATE Sim3" aligns it with
scale too, and its scale (ground truth / trajectory) shows an RGB-D sensor's depth-scale error
that no RGB-D tracking can observe. Peak memory is the process's
resident-set high-water mark after each sequence (ru_maxrss), so it only grows. A second table
gives, per sequence with ground truth, the accuracy of the loop-closure run's graph links by
type (odometry, loop, proximity, path, merged): count, median and worst error against the true
relative pose of the two keyframes, and how many are beyond 5 cm or 3 degrees.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.service.config import load_config, merge_overrides, parse_sets  # noqa: E402
from mnemoslam.service.evaluation import evaluate  # noqa: E402
from mnemoslam.service.pipeline import Pipeline  # noqa: E402
from mnemoslam.service.runner import run_dataset  # noqa: E402


def sequences(data: Path, synthetic_frames: int):
    yield "tum fr3/cabinet keyframes", data / "rgbd_dataset_freiburg3_cabinet_keyframes", {}
    yield "7-scenes redkitchen", data / "7scenes_redkitchen", {}
    yield "tum fr1/desk", data / "rgbd_dataset_freiburg1_desk", {}  # motion capture, fast handheld
    yield "kitti a (stereo)", data / "kitti_odometry_snippets/sequences/a", {}
    yield "kitti b (stereo)", data / "kitti_odometry_snippets/sequences/b", {}
    yield "euroc v101 head (stereo)", data / "euroc_v101_head", {}
    yield "synthetic loop", "synthetic:loop", {"max_frames": synthetic_frames}
    yield "synthetic loop + noise", "synthetic:loop", {"max_frames": synthetic_frames, "noise": True}
    # issue 12: 30 s handheld look-around at up to 60 deg/s per axis, 20 ms motion blur and the
    # Kinect disparity noise (the path's defaults), always whole (901 frames)
    yield "synthetic fastrot", "synthetic:fastrot", {}


def opened(entries, only: str | None = None):
    """(name, dataset) of the `entries` ((name, path, options), as `sequences` gives them) whose
    name contains `only`; a missing folder is skipped with a line on stderr."""
    for name, path, opts in entries:
        if only and only not in name:
            continue
        if not str(path).startswith("synthetic") and not Path(path).exists():
            print(f"skip {name}: {path} not found", file=sys.stderr)
            continue
        yield name, open_dataset(path, **opts)


def pipeline_fps(ds, config, limit=300) -> float:
    """Frames/s of the pipeline alone on pre-decoded frames."""
    frames = [ds.frame(i) for i in range(min(limit, len(ds)))]
    p = Pipeline(ds.calibration, config)
    t = time.perf_counter()
    for f in frames:
        p.process(f)
    return len(frames) / (time.perf_counter() - t)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", help="run sequences whose name contains this")
    ap.add_argument("--synthetic-frames", type=int, default=900)
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override (repeatable)")
    args = ap.parse_args()
    data = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data"))
    # SLAM alone: semantics (on by default; their cost: bench/bench_semantics.py) only with --set
    overrides = merge_overrides({"semantics": {"enabled": False}}, parse_sets(args.set))
    config = load_config(overrides=overrides)
    odometry_only = load_config(overrides=merge_overrides(overrides, {"loop": {"enabled": False}}))
    rows, link_rows = [], []
    for name, ds in opened(sequences(data, args.synthetic_frames), args.only):
        odom = run_dataset(ds, odometry_only, progress=True)
        out = run_dataset(ds, config, progress=True)
        ev = evaluate(ds.ground_truth, out.trajectory) if ds.ground_truth is not None else None
        ev_odom = evaluate(ds.ground_truth, odom.trajectory) if ds.ground_truth is not None else None
        ev_sim3 = evaluate(ds.ground_truth, out.trajectory, align="sim3") if ds.ground_truth is not None else None
        s = out.summary
        h, w = ds.calibration.camera.height, ds.calibration.camera.width
        rows.append((name, f"{w}x{h}", s.frames, s.tracked, s.lost, s.keyframes, s.merged,
                     f"{ev_odom.ate_rmse * 100:.2f}" if ev else "-",
                     f"{ev.ate_rmse * 100:.2f}" if ev else "-", f"{ev.ate_percent_of_path:.2f}" if ev else "-",
                     f"{ev_sim3.ate_rmse * 100:.2f} ({ev_sim3.scale:.3f})" if ev else "-",
                     f"{odom.summary.fps:.1f}", f"{s.fps:.1f}", f"{pipeline_fps(ds, config):.1f}",
                     f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f}"))
        for t in (out.links.types if out.links is not None else []):
            link_rows.append((name, t.kind, t.count, f"{t.median_cm:.2f}", f"{t.median_deg:.2f}", f"{t.max_cm:.2f}",
                              f"{t.max_deg:.2f}", t.beyond))
    head = ("sequence", "size", "frames", "tracked", "lost", "kf", "merged", "ATE odom cm", "ATE cm", "ATE %path",
            "ATE Sim3 cm (scale)", "fps e2e",
            "fps e2e+loops", "fps pipeline", "peak MB")
    print_table(head, rows)
    if link_rows:  # the run with loop closure: its graph's links against the true relative poses
        print()
        print_table(("sequence", "link type", "links", "median cm", "median deg", "worst cm", "worst deg",
                "beyond 5 cm/3 deg"), link_rows)
    return 0


def print_table(head, rows) -> None:
    """Rows of values as right-aligned columns under `head` (bench/bench_links.py prints its tables so too)."""
    widths = [max(len(str(r[i])) for r in rows + [head]) for i in range(len(head))]
    for r in [head] + rows:
        print("  ".join(str(v).rjust(wd) for v, wd in zip(r, widths)))


if __name__ == "__main__":
    sys.exit(main())
