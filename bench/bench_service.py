"""Frame -> pose latency through the running service: `mnemoslam serve` in its own
process, a camera client here streaming pre-rendered synthetic frames at a fixed rate,
and a subscriber here receiving the service's pose messages.

    python bench/bench_service.py [--frames 300] [--rate 30]

Latency is measured from just before the client encodes a frame to the arrival of the
pose message for it (encode + Zenoh + decode + queue + pipeline + publish). Also prints the
service's frames/s and drops as the REST API reports them.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.client.kernel import protocol  # noqa: E402
from mnemoslam.client.streamer import CameraStreamer  # noqa: E402
from mnemoslam.client.transport import ZenohSettings, open_session  # noqa: E402
from mnemoslam.service.demo import ServiceProcess  # noqa: E402


def run(frames, dataset, color: str, depth: str, rate: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        svc = ServiceProcess(Path(tmp) / "map.db").start()
        robot = f"bench-{color}-{depth}"
        sent: dict[int, float] = {}
        arrived: dict[int, float] = {}
        lock = threading.Lock()
        try:
            z = open_session(ZenohSettings(connect=[svc.endpoint]))

            def on_pose(sample):
                t = time.perf_counter()
                msg = protocol.decode_pose(sample.payload.to_bytes())
                with lock:
                    arrived[msg.seq] = t

            sub = z.declare_subscriber(protocol.KeySpace().pose(robot), on_pose)
            streamer = CameraStreamer(z, robot, dataset.calibration, color=color, depth=depth)
            streamer.wait_for_subscriber(10.0)
            t0 = time.perf_counter()
            for i, f in enumerate(frames):
                delay = t0 + i / rate - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                sent[i] = time.perf_counter()
                streamer.send(f, i)
            info = svc.wait_processed(robot, len(frames), timeout=120)
            time.sleep(0.5)
            streamer.close()
            sub.undeclare()
            z.close()
        finally:
            svc.stop()
    lat = np.array([arrived[i] - sent[i] for i in sent if i in arrived]) * 1e3
    return {"encoding": f"{color}/{depth}", "rate": rate, "poses": len(lat), "dropped": info["frames_dropped"],
            "p50": np.percentile(lat, 50), "p99": np.percentile(lat, 99), "fps": info["fps"],
            "pipeline_ms": info["processing_ms"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--rate", type=float, default=30.0)
    args = ap.parse_args()
    ds = open_dataset("synthetic:loop", max_frames=args.frames, noise=True)
    frames = [ds.frame(i) for i in range(len(ds))]  # rendered before the clock starts
    rows = [run(frames, ds, c, d, args.rate) for c, d in (("jpeg", "png"), ("jpeg", "raw"), ("raw", "raw"))]
    print(f"{'encoding':>10} {'Hz':>5} {'poses':>6} {'dropped':>8} {'p50 ms':>8} {'p99 ms':>8} {'svc fps':>8} "
          f"{'pipeline ms':>12}")
    for r in rows:
        print(f"{r['encoding']:>10} {r['rate']:>5.0f} {r['poses']:>6} {r['dropped']:>8} {r['p50']:>8.1f} "
              f"{r['p99']:>8.1f} {r['fps']:>8.1f} {r['pipeline_ms']:>12.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
