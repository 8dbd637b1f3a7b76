"""Real-time ingest: a real sequence streamed at camera rate through `mnemoslam serve`, client
included, on this machine — does the service keep every frame, and is the map it builds the
offline run's?

    python bench/bench_realtime.py [DATASET] [--rate 30] [--encoding auto|raw|jpeg|png]
                                   [--depth-encoding auto|raw|png] [--no-offline] [--set KEY=VALUE]

DATASET defaults to $MNEMOSLAM_DATA/7scenes_redkitchen (640×480 RGB-D, 1000 frames at 30 Hz).
The service runs in its own process with its default configuration (`--set` changes a key);
this process is the camera client (reads the dataset's files, encodes, publishes at `--rate`).
Prints frames sent / received / processed / dropped / rejected, the service's tracking
frames/s, CPU seconds per frame of the service (tracking process and its mapping child) and
of the client, the map backlog at the stream's end and how long it took to drain, and the
keyframe ATE over REST beside the offline run's (`mnemoslam run`, map update inline) with
their ratio.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.client.streamer import stream_dataset  # noqa: E402
from mnemoslam.client.transport import ZenohSettings  # noqa: E402
from mnemoslam.service.config import load_config, parse_sets  # noqa: E402
from mnemoslam.service.demo import ServiceProcess, keyframe_trajectory  # noqa: E402
from mnemoslam.service.evaluation import evaluate  # noqa: E402
from mnemoslam.service.runner import run_dataset  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process and of its waited-for children (the mapping child is not
    waited for while it runs, so its own pid is read as well)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return sum(int(v) for v in fields[11:15]) / TICK


def children(pid: int) -> list[int]:
    try:
        return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def main() -> int:
    default = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data")) / "7scenes_redkitchen"
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", nargs="?", default=str(default))
    ap.add_argument("--rate", type=float, default=30.0,
                    help="frames per second the client sends (camera rate); 0 = as fast as the service takes them")
    ap.add_argument("--encoding", default="auto", choices=["auto", "raw", "jpeg", "png"])
    ap.add_argument("--depth-encoding", default="auto", choices=["auto", "raw", "png"])
    ap.add_argument("--max-frames", type=int)
    ap.add_argument("--no-offline", action="store_true", help="skip the offline run (no ATE ratio)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="service config override")
    args = ap.parse_args()
    options = {"max_frames": args.max_frames} if args.max_frames else {}
    dataset = open_dataset(args.dataset, **options)
    overrides = parse_sets(args.set)
    robot = "rt"
    with tempfile.TemporaryDirectory(prefix="mnemoslam-rt-") as tmp:
        svc = ServiceProcess(Path(tmp) / "map.db", overrides, log_path=Path(tmp) / "service.log").start()
        try:
            mapping = children(svc.proc.pid)
            cpu0 = cpu_seconds(svc.proc.pid), sum(cpu_seconds(p) for p in mapping), time.process_time()
            stats = stream_dataset(dataset, robot, ZenohSettings(connect=[svc.endpoint]), rate=args.rate or None,
                                   color=args.encoding, depth=args.depth_encoding, progress=False,
                                   wait_for_subscriber=10.0)
            cpu_client = time.process_time() - cpu0[2]
            r = svc.wait_processed(robot, stats.frames, timeout=600)
            cpu_service = cpu_seconds(svc.proc.pid) - cpu0[0]
            backlog = r["map_backlog"]
            t = time.perf_counter()
            svc.wait_mapped(robot, timeout=900)
            drain = time.perf_counter() - t
            cpu_mapping = sum(cpu_seconds(p) for p in mapping) - cpu0[1]
            streamed = keyframe_trajectory(svc.api, svc.session_of(robot))
            log_errors = sum("ERROR" in line or "Traceback" in line
                             for line in svc.log_path.read_text(errors="replace").splitlines())
        finally:
            svc.stop()
    n = stats.frames
    asked = f"{args.rate:g} Hz" if args.rate else "the service's pace"
    print(f"{dataset.name}: {n} frames sent at {asked} ({stats.fps:.1f} frames/s achieved, "
          f"{stats.mbps:.0f} Mbit/s, encoding {stats.encoding})")
    print(f"service: received {r['frames_received']}, processed {r['frames_processed']}, "
          f"dropped {r['frames_dropped']}, rejected {sum(r['frames_rejected'].values())} "
          f"{r['frames_rejected'] or ''}; tracking {r['fps']:.1f} frames/s, {r['processing_ms']:.1f} ms/frame")
    print(f"CPU per frame: service tracking process {cpu_service / n * 1e3:.1f} ms, mapping child "
          f"{cpu_mapping / n * 1e3:.1f} ms (whole run incl. drain), client {cpu_client / n * 1e3:.1f} ms")
    print(f"map backlog at the end of the stream {backlog} keyframes, drained in {drain:.1f} s; "
          f"service log error lines: {log_errors}")
    ate = evaluate(dataset.ground_truth, streamed).ate_rmse if dataset.ground_truth is not None else float("nan")
    line = f"keyframe ATE over REST {ate * 100:.2f} cm ({len(streamed)} keyframes)"
    if not args.no_offline and dataset.ground_truth is not None:
        cfg = load_config(None, overrides)
        t = time.perf_counter()
        out = run_dataset(dataset, cfg, progress=False)
        secs = time.perf_counter() - t
        off = evaluate(dataset.ground_truth, out.keyframes).ate_rmse
        line += (f"; offline run {off * 100:.2f} cm ({len(out.keyframes)} keyframes, "
                 f"{len(out.results) / secs:.1f} frames/s with the map update inline); ratio {ate / off:.3f}")
    print(line)
    return 0 if r["frames_dropped"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
