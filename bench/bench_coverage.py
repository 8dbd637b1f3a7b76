"""Semantic coverage through the real service: a sequence streamed at a camera's pace into
`mnemoslam serve` (default configuration: semantics on, `source: auto`, the model for frames
without labels), then how much of the map the semantic map covers at the stream's end and
how fast the back-fill catches up (issue 24: >= 95 % of keyframes within 60 s of the end,
no frame dropped).

    python bench/bench_coverage.py [DATASET] [--rate 30] [--after 60] [--set KEY=VALUE]

DATASET defaults to $MNEMOSLAM_DATA/rgbd_dataset_freiburg1_desk. Prints the frames
received / processed / dropped, then the coverage (keyframes segmented / keyframes of the map)
at the stream's end and every 5 s after it, the seconds until 95 % and 100 %, the worker's
counts (processed live, deferred to the back-fill, back-filled, waits for tracking) and the
load average. While the stream runs it polls the robot's status: the deepest its frame queue
got, and a line per poll that found new drops (queue depth, frames processed, keyframes, what
the semantic worker had done), to tell when frames were dropped.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.client.streamer import stream_dataset  # noqa: E402
from mnemoslam.client.transport import ZenohSettings  # noqa: E402
from mnemoslam.service.config import merge_overrides, parse_sets  # noqa: E402
from mnemoslam.service.demo import ServiceProcess  # noqa: E402


def coverage(api) -> tuple[int, int, dict]:
    s = api.semantics()
    c = s.get("coverage") or {"segmented": 0, "keyframes": 0}
    return c["segmented"], c["keyframes"], s


class Watch(threading.Thread):
    """Polls the robot's status while the stream runs (every `period` s): the deepest its
    frame queue got, and when frames were dropped (with the queue depth and what the semantic
    worker had done by then), so a drop can be told apart: at the model's load, during live
    segmentation, or elsewhere."""

    def __init__(self, api, robot: str, t0: float, period: float = 0.25):
        super().__init__(daemon=True)
        self.api, self.robot, self.t0, self.period = api, robot, t0, period
        self.stop = threading.Event()
        self.max_depth = 0
        self.drops: list[str] = []

    def run(self) -> None:
        dropped = 0
        while not self.stop.wait(self.period):
            try:
                r = self.api.robot(self.robot)
            except Exception:  # not admitted yet
                continue
            self.max_depth = max(self.max_depth, r.get("queue_depth") or 0)
            if (r.get("frames_dropped") or 0) > dropped:
                w = (self.api.semantics().get("worker") or {})
                self.drops.append(f"+{time.monotonic() - self.t0:5.1f} s: {r['frames_dropped'] - dropped} dropped "
                                  f"(queue {r.get('queue_depth')}, {r.get('frames_processed')} processed, "
                                  f"{r.get('processing_ms')} ms/frame, keyframes {r.get('keyframes')}; worker "
                                  f"processed {w.get('processed')}, deferred {w.get('deferred')})")
                dropped = r["frames_dropped"]


def main() -> int:
    data = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data"))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", nargs="?", default=str(data / "rgbd_dataset_freiburg1_desk"))
    ap.add_argument("--rate", type=float, default=30.0, help="frames per second streamed (a camera's pace)")
    ap.add_argument("--after", type=float, default=60.0, help="seconds to watch the back-fill after the stream")
    ap.add_argument("--log", help="keep the service's log here (default: in the run's temporary folder)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="service config override")
    args = ap.parse_args()
    ds = open_dataset(args.dataset)
    with tempfile.TemporaryDirectory() as d:
        # the robot stays listed while the back-fill is watched (its counts are read at the end)
        config = merge_overrides({"service": {"idle_timeout": 3600.0}}, parse_sets(args.set))
        svc = ServiceProcess(Path(d) / "map.db", config, log_path=Path(args.log or Path(d) / "service.log")).start()
        try:
            status = svc.api.semantics()
            print(f"{ds.name}: {len(ds)} frames at {args.rate:g} Hz; semantics source {status['source']}, "
                  f"model {status['model']}; load average {os.getloadavg()[0]:.1f}", flush=True)
            t0 = time.monotonic()
            watch = Watch(svc.api, "r1", t0)
            watch.start()
            stream_dataset(ds, "r1", ZenohSettings(connect=[svc.endpoint]), rate=args.rate, progress=False,
                           wait_for_subscriber=10.0)
            end = time.monotonic()
            svc.wait_processed("r1", len(ds), timeout=120)
            watch.stop.set()
            watch.join()
            print(f"streamed in {end - t0:.1f} s; the robot's frame queue at most {watch.max_depth} deep "
                  f"(polled every {watch.period:g} s)", flush=True)
            for line in watch.drops[:8]:
                print("  drop " + line, flush=True)
            if len(watch.drops) > 8:
                print(f"  ... and {len(watch.drops) - 8} more polls that found drops", flush=True)
            first = {}
            while True:
                seg, kf, status = coverage(svc.api)
                robot = svc.api.robot("r1")
                dt = time.monotonic() - end
                share = seg / kf if kf else 0.0
                print(f"  +{dt:5.1f} s: {seg}/{kf} keyframes segmented ({100 * share:.0f} %), "
                      f"frames processed {robot.get('frames_processed')}, dropped {robot.get('frames_dropped')}",
                      flush=True)
                for goal in (0.95, 1.0):
                    if share >= goal and goal not in first:
                        first[goal] = dt
                if dt >= args.after or (kf and seg == kf):
                    break
                time.sleep(5.0)
            w = status.get("worker") or {}
            print(f"frames: received {robot.get('frames_received')}, processed {robot.get('frames_processed')}, "
                  f"dropped {robot.get('frames_dropped')}; keyframes {kf}")
            print(f"coverage: 95 % after {first.get(0.95, float('nan')):.1f} s, 100 % after "
                  f"{first.get(1.0, float('nan')):.1f} s of the stream's end (watched {args.after:g} s)")
            print(f"worker: processed {w.get('processed')} (back-filled {w.get('backfilled')}), deferred "
                  f"{w.get('deferred')}, dropped {w.get('dropped')}, errors {w.get('errors')}, waited for tracking "
                  f"{w.get('waits')} times ({w.get('wait_s')} s), "
                  f"{w.get('ms_per_keyframe') or 0:.0f} ms per keyframe, objects {w.get('objects')}; "
                  f"load average {os.getloadavg()[0]:.1f}")
        finally:
            svc.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
