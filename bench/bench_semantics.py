"""Tracking frames/s with semantics on (the ONNX model on keyframes, on the semantic
worker's thread) vs off, on a real sequence: does segmenting keyframes slow tracking?

    python bench/bench_semantics.py [DATASET] [--frames 300] [--rate HZ] [--set KEY=VALUE]

DATASET defaults to $MNEMOSLAM_DATA/7scenes_redkitchen. The frames are decoded first (not
timed); each configuration then runs the same frames through a pipeline built as the
service builds it (semantic worker on its own thread; the map update in a child process as
the service's `loop.process: true` runs it, or on a thread with `--mapping thread`), timing
`Pipeline.process` only (tracking; the worker and the map
update run concurrently), then waits for the worker and the map update to finish (not
timed). After a warm-up run, off and on alternate (off, on, off, ..., `--rounds` on runs).
Prints frames/s off and on, the ratio of their medians (issue 14: on within 10 % of off), the
keyframes segmented and dropped, and the model's time per keyframe. Here the worker works
whenever it has a keyframe (at most `semantics.max_duty` of the time), as in offline runs.

With `--rate HZ` the frames go through a robot's session as in the service (`RobotSession`:
its 1 s frame queue, dropping the oldest when full), put at a camera's pace, and the worker
has the service's probe (tracking first: it waits while the robot's queue holds frames or its
tracking has no margin, `semantics.yield_queue`, `min_slack`). Then per run: the pipeline's
mean and p95 time per frame, the share of the time tracking was busy, frames dropped, and the
keyframes segmented while the frames came (the rest wait for the back-fill); the ratio of
the median mean times on / off.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.client.kernel.protocol import Limits  # noqa: E402
from mnemoslam.service.builder import build_pipeline, build_semantics  # noqa: E402
from mnemoslam.service.config import load_config, merge_overrides, parse_sets  # noqa: E402
from mnemoslam.service.mapping.process import MappingProcess  # noqa: E402
from mnemoslam.service.semantics.segmentation import semantics_status  # noqa: E402
from mnemoslam.service.session import RobotSession  # noqa: E402
from mnemoslam.storage import MapStore  # noqa: E402


def run(frames, ds, config) -> tuple[float, dict | None]:
    with tempfile.TemporaryDirectory() as d, MapStore(Path(d) / "map.db") as store:
        mapping = MappingProcess(store.path, config.loop, config.memory) if config.loop.process else None
        p = build_pipeline(store, "bench", ds.calibration, config, mapping=mapping, background=True)
        t = time.perf_counter()
        for f in frames:
            p.process(f)
        seconds = time.perf_counter() - t
        p.close()
        if mapping is not None:
            mapping.close()
        stats = p.semantics.stats() if p.semantics is not None else None
        if stats is not None:
            stats["objects_stored"] = store.count_objects()
    return len(frames) / seconds, stats


def run_paced(frames, ds, config, rate: float) -> tuple[dict, dict | None]:
    """The frames through a robot's session at `rate` Hz, as the service runs them: ({"ms":
    mean time per frame, "p95", "busy": tracking's busy share, "dropped"}, the worker's counts
    at the stream's end, or None without semantics)."""
    with tempfile.TemporaryDirectory() as d, MapStore(Path(d) / "map.db") as store:
        mapping = MappingProcess(store.path, config.loop, config.memory) if config.loop.process else None
        holder: dict = {}
        worker, off = build_semantics(store, config, background=True)
        if worker is not None:  # the service's probe
            s = config.semantics
            worker.tracking_busy = lambda margin=True: any(
                r.needs_cpu(int(s.yield_queue), float(s.min_slack) if margin else 0.0) for r in holder.values())
        times: list[float] = []
        done = threading.Event()

        def on_result(session, frame, result) -> None:
            times.append(sum(result.timings.values()))
            if session.stats.processed + session.stats.dropped_queue >= len(frames):
                done.set()

        session = RobotSession("bench", config, ds.calibration, Limits(),
                               lambda cal: build_pipeline(store, "bench", cal, config, mapping=mapping,
                                                          background=True, semantics=(worker, off)),
                               on_result)
        holder["bench"] = session
        t0 = time.perf_counter()
        for k, f in enumerate(frames):
            time.sleep(max(0.0, t0 + k / rate - time.perf_counter()))
            session.submit(k, f)
        while not done.wait(0.05):
            if session.stats.processed + session.stats.dropped_queue >= len(frames):
                break
        seconds = time.perf_counter() - t0
        stats = worker.stats() if worker is not None else None
        out = {"ms": float(np.mean(times)), "p95": float(np.percentile(times, 95)),
               "busy": float(np.sum(times)) / 1e3 / seconds, "dropped": session.stats.dropped_queue,
               "keyframes": session.stats.keyframes}
        session.stop()
        if worker is not None:
            worker.close(timeout=300.0)  # the queued keyframes (the rest is the back-fill's: not waited for here)
        if mapping is not None:
            mapping.close()
    return out, stats


def main_paced(frames, ds, on, off, rounds: int, rate: float) -> None:
    run_paced(frames, ds, off, rate)  # warm-up
    res = {"off": [], "on": []}
    stats = None
    for k in range(2 * rounds + 1):
        name = "on" if k % 2 else "off"
        out, st = run_paced(frames, ds, on if name == "on" else off, rate)
        res[name].append(out)
        stats = st or stats
        print(f"  {name}: {out['ms']:.1f} ms per frame (p95 {out['p95']:.1f}), tracking busy "
              f"{100 * out['busy']:.0f} % of the time, {out['dropped']} frames dropped, {out['keyframes']} keyframes"
              + (f"; segmented while streaming {st['processed']}, deferred {st['deferred']}, waited for tracking "
                 f"{st['waits']} times ({st['wait_s']} s)" if st else ""), flush=True)
    med = {k: float(np.median([r["ms"] for r in v])) for k, v in res.items()}
    print(f"time per frame at {rate:g} Hz: off median {med['off']:.1f} ms, on median {med['on']:.1f} ms; "
          f"on/off = {med['on'] / med['off']:.3f}; dropped off {[r['dropped'] for r in res['off']]}, "
          f"on {[r['dropped'] for r in res['on']]}; load average {os.getloadavg()[0]:.1f}")


def main() -> None:
    data = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data"))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", nargs="?", default=str(data / "7scenes_redkitchen"))
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--rounds", type=int, default=2, help="runs with semantics on, each between two off runs")
    ap.add_argument("--rate", type=float, default=0.0,
                    help="frames/s through a robot's session as in the service (tracking first); 0 = back to back")
    ap.add_argument("--mapping", choices=["process", "thread"], default="process",
                    help="the map update in a child process, as the service runs it (loop.process, the default), "
                         "or on a thread of this process")
    args = ap.parse_args()
    ds = open_dataset(args.dataset)
    frames = [ds.frame(i) for i in range(min(args.frames, len(ds)))]
    base = parse_sets(args.set)
    process = args.mapping == "process"
    off = load_config(None, merge_overrides(base, {"loop": {"process": process}, "semantics": {"enabled": False}}))
    on = load_config(None, merge_overrides(base, {"loop": {"process": process},
                                                  "semantics": {"enabled": True, "source": "model"}}))
    status = semantics_status(on.semantics)
    if not status["enabled"]:
        sys.exit(f"semantics cannot run: {status['reason']}")
    print(f"{ds.name}: {len(frames)} frames, model {status['model']}, {on.semantics.threads} onnxruntime thread(s), "
          f"load average {os.getloadavg()[0]:.1f}")
    if args.rate > 0:
        main_paced(frames, ds, on, off, args.rounds, args.rate)
        return
    run(frames, ds, off)  # warm-up (not counted): the first run in a process is slower (caches, allocations)
    fps = {"off": [], "on": []}
    stats = None
    for k in range(2 * args.rounds + 1):  # off, on, off, on, ..., off: the machine's load drifts
        name = "on" if k % 2 else "off"
        f, st = run(frames, ds, on if name == "on" else off)
        fps[name].append(f)
        stats = st or stats
    med = {k: float(np.median(v)) for k, v in fps.items()}
    print(f"tracking frames/s: off {' / '.join(f'{x:.1f}' for x in fps['off'])} (median {med['off']:.1f}), "
          f"on {' / '.join(f'{x:.1f}' for x in fps['on'])} (median {med['on']:.1f}); "
          f"on/off = {med['on'] / med['off']:.3f}")
    print(f"semantic worker: {stats['processed']} keyframes segmented + fused, "
          f"{stats['dropped']} dropped (queue full), {stats['errors']} errors, "
          f"{stats['ms_per_keyframe'] or 0:.0f} ms per keyframe, {stats['objects_stored']} objects stored; "
          f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
