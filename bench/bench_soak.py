"""Soak: a real sequence streamed into `mnemoslam serve` again and again for N minutes, each time
as a new robot — does the service's memory stay flat?

    python bench/bench_soak.py [DATASET] [--minutes 20] [--connected 3] [--rate 30]
                               [--max-frames N] [--set KEY=VALUE] [--service-env KEY=VALUE]

DATASET defaults to $MNEMOSLAM_DATA/7scenes_redkitchen (1000 frames at 30 Hz, ~33 s a pass).
The service runs in its own process with its default configuration (`--set` changes a key,
`--service-env` sets an environment variable of its process); this process is the camera
client: one pass after another, each as a new robot (`soak-1`, `soak-2`, ...) on a Zenoh
session of its own, starting a new robot only while fewer than `--connected` robots have a
slot in the service (a robot's slot is freed `service.idle_timeout` s after its last frame,
60 s by default, so with 33 s passes 2-3 robots are connected at once).

Prints, once a minute: the resident memory (VmRSS, from /proc) of the service's process and of
each of its child processes (the mapping child), the robots connected, and the frames the
service has processed / dropped / rejected so far (summed over every robot: the bench keeps
each robot's last REST status, so robots that have expired still count). At the end: the
totals, each process's growth from minute 5 (`--warmup`) to the end and its least-squares
slope over that span in MB per minute (done-when, issue 24: ≤ 50 MB of growth over a
20-minute soak for the service and likewise for the mapping child).
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.client.planner import ApiError  # noqa: E402
from mnemoslam.client.streamer import stream_dataset  # noqa: E402
from mnemoslam.client.transport import ZenohSettings  # noqa: E402
from mnemoslam.service.config import parse_sets  # noqa: E402
from mnemoslam.service.demo import ServiceProcess  # noqa: E402


def rss_mb(pid: int, field: str = "VmRSS") -> float | None:
    """VmRSS (or another kB field of /proc/PID/status: RssAnon, RssShmem) of a process in MB
    (None once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def shm_mb() -> float:
    """Zenoh's shared-memory segments left in /dev/shm (MB)."""
    try:
        return sum(p.stat().st_size for p in Path("/dev/shm").glob("*.zenoh")) / 2**20
    except OSError:
        return 0.0


def descendants(pid: int) -> list[int]:
    """The process's children and theirs, from /proc/PID/task/*/children."""
    out: list[int] = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tasks:
        try:
            kids = [int(p) for p in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()]
        except OSError:
            continue
        for k in kids:
            out += [k, *descendants(k)]
    return out


def process_name(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return "?"


class Tally:
    """Each robot's last REST status (robots expire from /robots once idle: their last status stays)."""

    def __init__(self, svc: ServiceProcess):
        self.svc = svc
        self.last: dict[str, dict] = {}
        self.connected = 0
        self.backlog = 0  # keyframes waiting for the map update, over the connected robots
        self.rejected_before_slot = 0  # messages refused before reaching a session (/status)
        self._lock = threading.Lock()

    def poll(self) -> None:
        try:
            robots = self.svc.api.robots()
            status = self.svc.api.health()
        except (OSError, ApiError):
            return
        with self._lock:
            for r in robots:
                self.last[r["robot"]] = r
            self.connected = len(robots)
            self.backlog = sum(int(r.get("map_backlog") or 0) for r in robots)
            self.rejected_before_slot = int(status.get("rejected_total", self.rejected_before_slot) or 0)

    def totals(self) -> dict:
        with self._lock:
            rs = list(self.last.values())
            return {"robots": len(rs), "received": sum(r["frames_received"] for r in rs),
                    "processed": sum(r["frames_processed"] for r in rs),
                    "dropped": sum(r["frames_dropped"] for r in rs),
                    "rejected": sum(sum(r["frames_rejected"].values()) for r in rs),
                    "connected": self.connected, "backlog": self.backlog}


def slope_per_minute(ts: list[float], mb: list[float]) -> float:
    if len(ts) < 2:
        return float("nan")
    return float(np.polyfit(np.array(ts) / 60.0, np.array(mb), 1)[0])


def main() -> int:
    default = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data")) / "7scenes_redkitchen"
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", nargs="?", default=str(default))
    ap.add_argument("--minutes", type=float, default=20.0, help="how long to stream (a pass running then finishes)")
    ap.add_argument("--connected", type=int, default=3,
                    help="start a new robot only while fewer than this many have a slot in the service")
    ap.add_argument("--rate", type=float, default=30.0, help="frames per second of each pass (camera rate)")
    ap.add_argument("--max-frames", type=int, help="frames per pass (default: the whole sequence)")
    ap.add_argument("--warmup", type=float, default=5.0, help="minute from which growth is measured")
    ap.add_argument("--every", type=float, default=60.0, help="seconds between RSS lines")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="service config override")
    ap.add_argument("--service-env", action="append", default=[], metavar="KEY=VALUE",
                    help="environment variable of the service's process (e.g. MALLOC_ARENA_MAX=2)")
    args = ap.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # (the service is stopped on the way out)
    options = {"max_frames": args.max_frames} if args.max_frames else {}
    dataset = open_dataset(args.dataset, **options)
    overrides = parse_sets(args.set)
    saved_env = dict(os.environ)
    os.environ.update(dict(kv.split("=", 1) for kv in args.service_env))
    with tempfile.TemporaryDirectory(prefix="mnemoslam-soak-") as tmp:
        svc = ServiceProcess(Path(tmp) / "map.db", overrides, log_path=Path(tmp) / "service.log").start()
        os.environ.clear()
        os.environ.update(saved_env)
        tally = Tally(svc)
        samples: list[tuple[float, float | None, dict[int, float | None], dict]] = []  # (t, serve, kids, totals)
        names: dict[int, str] = {}
        stop = threading.Event()
        t0 = time.monotonic()

        def sample() -> None:
            tally.poll()
            kids = {p: rss_mb(p) for p in descendants(svc.proc.pid)}
            for p in kids:
                names.setdefault(p, process_name(p))
            t = time.monotonic() - t0
            samples.append((t, rss_mb(svc.proc.pid), kids, tally.totals()))
            tot = samples[-1][3]
            kid_text = ", ".join(f"child {p} {v:.0f} MB" for p, v in kids.items() if v is not None) or "no child"
            pid = svc.proc.pid
            print(f"min {t / 60:5.1f}: serve {samples[-1][1] or 0:6.0f} MB (anon {rss_mb(pid, 'RssAnon') or 0:.0f}, "
                  f"shared memory {rss_mb(pid, 'RssShmem') or 0:.0f}), {kid_text}; /dev/shm zenoh {shm_mb():.0f} MB; "
                  f"robots {tot['robots']} "
                  f"({tot['connected']} connected), frames processed {tot['processed']}, dropped {tot['dropped']}, "
                  f"rejected {tot['rejected']}; map backlog {tot['backlog']} keyframes", flush=True)

        def watch() -> None:
            next_line = 0.0
            while not stop.is_set():
                if time.monotonic() - t0 >= next_line:
                    sample()
                    next_line += args.every
                else:
                    tally.poll()
                stop.wait(2.0)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        sent = passes = 0
        client_rejected = 0
        try:
            while time.monotonic() - t0 < args.minutes * 60:
                while tally.connected >= args.connected and time.monotonic() - t0 < args.minutes * 60:
                    time.sleep(1.0)
                    tally.poll()
                if time.monotonic() - t0 >= args.minutes * 60:
                    break
                passes += 1
                stats = stream_dataset(dataset, f"soak-{passes}", ZenohSettings(connect=[svc.endpoint]),
                                       rate=args.rate or None, progress=False, wait_for_subscriber=10.0)
                sent += stats.frames
                client_rejected += stats.rejected_total
                tally.poll()
            time.sleep(5.0)  # the last frames through the queue
            stop.set()
            watcher.join()
            sample()
        finally:
            stop.set()
            svc.stop()
    tot = samples[-1][3]
    print(f"{dataset.name}: {passes} passes as new robots in {samples[-1][0] / 60:.1f} min, {sent} frames sent "
          f"at {args.rate:g} Hz; service: received {tot['received']}, processed {tot['processed']}, dropped "
          f"{tot['dropped']}, rejected {tot['rejected']} (+{tally.rejected_before_slot} refused before a slot)")
    warm = [s for s in samples if s[0] >= args.warmup * 60 - 1]
    if len(warm) < 2:
        print(f"run shorter than the warm-up ({args.warmup:g} min): no growth figures")
        return 0
    series = {"serve": [(t, v) for t, v, _, _ in warm if v is not None]}
    for pid in sorted({p for _, _, kids, _ in warm for p in kids}):
        series[f"child {pid} ({names.get(pid, '?')})"] = [(t, kids[pid]) for t, _, kids, _ in warm
                                                         if kids.get(pid) is not None]
    print(f"RSS growth from minute {warm[0][0] / 60:.1f} to {warm[-1][0] / 60:.1f}:")
    for name, pts in series.items():
        if len(pts) < 2:
            continue
        ts, mb = [t for t, _ in pts], [v for _, v in pts]
        print(f"  {name}: {mb[0]:.0f} -> {mb[-1]:.0f} MB, growth {mb[-1] - mb[0]:+.1f} MB "
              f"(slope {slope_per_minute(ts, mb):+.2f} MB/min, peak {max(mb):.0f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
