"""Render speed of the synthetic scene (RGB + depth + labels + instances per frame).

    .venv/bin/python bench/bench_render.py [--frames 150] [--all-cores] [--noise] [--png DIR]

Pins itself to one CPU core and one OpenCV thread (unless --all-cores), renders frames
along the "loop" path at 640x480 and 320x240 and prints ms/frame (p50, p90) and frames/s.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150, help="frames per resolution (default 150)")
    ap.add_argument("--trajectory", default="loop")
    ap.add_argument("--all-cores", action="store_true", help="do not pin to one core / one OpenCV thread")
    ap.add_argument("--noise", action="store_true", help="also time SyntheticDataset.frame() with noise=True")
    ap.add_argument("--png", metavar="DIR", help="write a few rendered frames there")
    args = ap.parse_args()

    import cv2

    if not args.all_cores:
        cv2.setNumThreads(1)
        if hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

    from mnemoslam.client.kernel.frames import PinholeCamera
    from mnemoslam.client.synthetic import SyntheticDataset, SyntheticScene, trajectory

    t0 = time.perf_counter()
    scene = SyntheticScene(0)
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    SyntheticScene(1)
    build2 = time.perf_counter() - t0
    print(f"scene build: {build * 1000:.0f} ms (first, incl. OpenCV warm-up), {build2 * 1000:.0f} ms (second seed); "
          f"{len(scene.quads)} quads, atlas {scene.atlas.shape[1]}x{scene.atlas.shape[0]}, "
          f"{len(scene.objects)} objects")
    print(f"cpu: {'all cores' if args.all_cores else 'pinned to 1 core, cv2 1 thread'}; "
          f"load average {os.getloadavg()[0]:.2f} (other processes slow the numbers down)")

    path = trajectory(args.trajectory)
    ts = np.linspace(0, path.duration, args.frames, endpoint=False)
    poses = path(ts)
    for w, h in ((640, 480), (320, 240)):
        cam = PinholeCamera(525.0 * w / 640, 525.0 * w / 640, (w - 1) / 2, (h - 1) / 2, w, h)
        for p in poses[:5]:  # warm-up (workspace allocation)
            scene.render(p, cam)
        times = []
        for p in poses:
            t0 = time.perf_counter()
            scene.render(p, cam)
            times.append(time.perf_counter() - t0)
        ms = np.array(times) * 1000
        print(f"render {w}x{h}: p50 {np.percentile(ms, 50):6.2f} ms  p90 {np.percentile(ms, 90):6.2f} ms  "
              f"max {ms.max():6.2f} ms  -> {1000 / ms.mean():6.1f} frames/s (mean over {len(ms)} frames)")
    if args.noise:
        ds = SyntheticDataset(args.trajectory, noise=True, max_frames=args.frames)
        ds.frame(0)
        times = []
        for i in range(len(ds)):
            t0 = time.perf_counter()
            ds.frame(i)
            times.append(time.perf_counter() - t0)
        ms = np.array(times) * 1000
        print(f"dataset frame 640x480 noise=True: p50 {np.percentile(ms, 50):6.2f} ms  "
              f"p90 {np.percentile(ms, 90):6.2f} ms  -> {1000 / ms.mean():6.1f} frames/s")
    if args.png:
        out = Path(args.png)
        out.mkdir(parents=True, exist_ok=True)
        cam = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)
        for k in range(0, len(poses), max(1, len(poses) // 6)):
            r = scene.render(poses[k], cam)
            cv2.imwrite(str(out / f"synth_{args.trajectory}_{k:04d}.png"), r.rgb)
        print(f"wrote frames to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
