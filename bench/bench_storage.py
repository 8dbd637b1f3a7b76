"""Write and read speed of the SQLite long-term memory.

    .venv/bin/python bench/bench_storage.py [--keyframes 5000] [--features 500] [--images] [--rate HZ] [--db FILE]

Adds keyframes with random features (N×2 float32 keypoints, N×32 uint8 descriptors,
N×3 float32 points), an odometry link and a small statistics dict each — one transaction
per keyframe, as the service does — and prints keyframes/s, p50/p99 ms per add_keyframe,
p50 ms of load_features for random nodes, a bbox query and the database size.
Unpaced, the writer outruns the background WAL checkpointer (hundreds of MB/s with
--images), so the writer is held off now and then to keep the WAL bounded (the max);
--rate shows the latency at a service-like keyframe rate.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--keyframes", type=int, default=5000)
    ap.add_argument("--features", type=int, default=500)
    ap.add_argument("--loads", type=int, default=2000, help="random load_features calls")
    ap.add_argument("--images", action="store_true",
                    help="also store a ~40 kB JPEG-sized blob and a ~200 kB PNG-sized blob per keyframe")
    ap.add_argument("--rate", type=float, default=0.0,
                    help="pace the writes at this many keyframes/s (default: as fast as possible)")
    ap.add_argument("--db", help="database file (default: a temporary one, deleted afterwards)")
    args = ap.parse_args()

    from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
    from mnemoslam.storage import KeyframeRecord, MapStore

    tmp = None
    if args.db:
        path = Path(args.db)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="bench_storage_")
        path = Path(tmp.name) / "bench.db"
    rng = np.random.default_rng(0)
    n, k = args.features, args.keyframes
    cal = Calibration(PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480))
    # Pre-generate a pool of feature sets so the timing measures storage, not the RNG.
    pool = []
    for _ in range(16):
        pts = rng.normal(0, 2, (n, 3)).astype(np.float32)
        pts[rng.random(n) < 0.2] = np.nan
        pool.append(((rng.random((n, 2)) * (640, 480)).astype(np.float32),
                     rng.integers(0, 256, (n, 32), dtype=np.uint8), pts))
    jpeg = b"\xff\xd8\xff" + rng.bytes(40_000) if args.images else None
    png = b"\x89PNG\r\n\x1a\n" + rng.bytes(200_000) if args.images else None

    with MapStore(path) as store:
        sid = store.begin_session("bench", cal)
        step = np.eye(4)
        step[0, 3] = 0.05
        P = np.eye(4)
        prev = None
        times = np.empty(k)
        t_start = time.perf_counter()
        for i in range(k):
            kp, desc, pts = pool[i % len(pool)]
            P = P @ step
            rec = KeyframeRecord(sid, i * 0.5, P.copy(), kp, desc, pts, image_jpeg=jpeg, depth_png=png,
                                 odom_link=None if prev is None else (prev, step, np.eye(6) * 1e4),
                                 statistics={"inliers": 200 + i % 50, "track_ms": 12.5})
            if args.rate > 0:
                time.sleep(max(0.0, t_start + i / args.rate - time.perf_counter()))
            t0 = time.perf_counter()
            prev = store.add_keyframe(rec)
            times[i] = time.perf_counter() - t0
        total = time.perf_counter() - t_start

        ids = rng.integers(1, prev + 1, args.loads)
        lt = np.empty(len(ids))
        for j, nid in enumerate(ids):
            t0 = time.perf_counter()
            store.load_features(int(nid))
            lt[j] = time.perf_counter() - t0
        t0 = time.perf_counter()
        found = store.count_nodes(bbox=((10.0, -1.0, -1.0), (20.0, 1.0, 1.0)))
        page = store.nodes(bbox=((10.0, -1.0, -1.0), (20.0, 1.0, 1.0)), limit=100)
        bbox_ms = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        traj = store.trajectory(sid)
        traj_ms = (time.perf_counter() - t0) * 1e3
        st = store.stats()
        ok = store.integrity_check()
    size_after_close = path.stat().st_size

    ms = times * 1e3
    paced = f", paced at {args.rate:g}/s" if args.rate > 0 else ""
    print(f"storage bench: {k} keyframes x {n} features{' + image blobs' if args.images else ''}{paced}, "
          "SQLite WAL, synchronous=NORMAL")
    print(f"  add_keyframe    {k / total:8.0f} keyframes/s   p50 {np.percentile(ms, 50):.3f} ms   "
          f"p99 {np.percentile(ms, 99):.3f} ms   max {ms.max():.1f} ms")
    print(f"  load_features   p50 {np.percentile(lt * 1e3, 50):.3f} ms   p99 {np.percentile(lt * 1e3, 99):.3f} ms  "
          f"({len(ids)} random nodes)")
    print(f"  bbox query      {found} nodes in box, count + first page {bbox_ms:.2f} ms ({len(page)} returned)")
    print(f"  trajectory      {len(traj)} poses in {traj_ms:.1f} ms")
    print(f"  database        {st['file_bytes'] / 1e6:.1f} MB incl. WAL while open, "
          f"{size_after_close / 1e6:.1f} MB after close ({size_after_close / k / 1e3:.1f} kB per keyframe); "
          f"integrity {ok}")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
