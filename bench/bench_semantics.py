"""Tracking frames/s with semantics on (the ONNX model on keyframes, on the semantic
worker's thread) vs off, on a real sequence: does segmenting keyframes slow tracking?

    python bench/bench_semantics.py [DATASET] [--frames 300] [--set KEY=VALUE]

DATASET defaults to $MNEMOSLAM_DATA/7scenes_redkitchen. The frames are decoded first (not
timed); each configuration then runs the same frames through a pipeline built as the
service builds it (semantic worker on its own thread; map update on a thread here, as with
`loop.process: false`), timing `Pipeline.process` only (tracking; the worker and the map
update run concurrently), then waits for the worker and the map update to finish (not
timed). Prints frames/s off and on, their ratio (issue 14: on within 10 % of off), the
keyframes segmented and dropped, and the model's time per keyframe.
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

from client.datasets import open_dataset  # noqa: E402
from service.builder import build_pipeline  # noqa: E402
from service.config import load_config, merge_overrides, parse_sets  # noqa: E402
from service.semantics.segmentation import semantics_status  # noqa: E402
from storage import MapStore  # noqa: E402


def run(frames, ds, config) -> tuple[float, dict | None]:
    with tempfile.TemporaryDirectory() as d, MapStore(Path(d) / "map.db") as store:
        p = build_pipeline(store, "bench", ds.calibration, config, background=True)
        t = time.perf_counter()
        for f in frames:
            p.process(f)
        seconds = time.perf_counter() - t
        p.close()
        stats = p.semantics.stats() if p.semantics is not None else None
        if stats is not None:
            stats["objects_stored"] = store.count_objects()
    return len(frames) / seconds, stats


def main() -> None:
    data = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data"))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", nargs="?", default=str(data / "7scenes_redkitchen"))
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    ds = open_dataset(args.dataset)
    frames = [ds.frame(i) for i in range(min(args.frames, len(ds)))]
    base = parse_sets(args.set)
    off = load_config(None, merge_overrides(base, {"loop": {"process": False}}))
    on = load_config(None, merge_overrides(base, {"loop": {"process": False},
                                                  "semantics": {"enabled": True, "source": "model"}}))
    status = semantics_status(on.semantics)
    if not status["enabled"]:
        sys.exit(f"semantics cannot run: {status['reason']}")
    print(f"{ds.name}: {len(frames)} frames, model {status['model']}, {on.semantics.threads} onnxruntime thread(s), "
          f"load average {os.getloadavg()[0]:.1f}")
    fps_off, _ = run(frames, ds, off)
    fps_on, stats = run(frames, ds, on)
    fps_off2, _ = run(frames, ds, off)  # again: the machine's load drifts
    off_mean = (fps_off + fps_off2) / 2
    print(f"tracking frames/s: off {fps_off:.1f} / {fps_off2:.1f}, on {fps_on:.1f}; on/off = {fps_on / off_mean:.3f}")
    print(f"semantic worker: {stats['processed']} keyframes segmented + fused, {stats['dropped']} dropped (queue full), "
          f"{stats['errors']} errors, {stats['ms_per_keyframe'] or 0:.0f} ms per keyframe, "
          f"{stats['objects_stored']} objects stored; load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
