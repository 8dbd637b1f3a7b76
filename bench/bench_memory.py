"""Memory management on a long run: a sequence played back and forth (`--passes`), once with
working memory bounded (`memory.max_wm_nodes`) and once unbounded, offline with the map
update inline (the same pipeline as `mnemoslam run`).

    python bench/bench_memory.py [DATASET] [--passes 10] [--max-wm 100] [--only bounded|unbounded]
                                 [--set memory.rehearsal=true ...]

DATASET defaults to $MNEMOSLAM_DATA/7scenes_redkitchen; `--set` overrides config keys of both
runs. Prints per run: the map's nodes (keyframes not merged by rehearsal) after the first
pass and in all, the largest WM, LTM at the end, transfers / retrievals, map update
median and p99 over keyframes 100-300 and over the last 200 (and their ratio), loop links
whose older node had been transferred to LTM and retrieved before the link (in the last two
passes), the ATE of the whole run and, for the two runs, the ATE ratio bounded / unbounded
and peak RSS. Each run's updates.csv is kept in --out.
"""
from __future__ import annotations

import argparse
import csv
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.client.datasets.passes import Passes  # noqa: E402
from mnemoslam.service.config import load_config, merge_overrides, parse_sets  # noqa: E402
from mnemoslam.service.evaluation import evaluate  # noqa: E402
from mnemoslam.service.runner import run_dataset  # noqa: E402
from mnemoslam.storage import LinkType, MapStore  # noqa: E402


def run(dataset, passes: int, max_wm: int, out: Path, overrides: dict) -> dict:
    ds = Passes(dataset, passes)
    cfg = load_config(None, merge_overrides(overrides, {"memory": {"max_wm_nodes": max_wm}}))
    t = time.perf_counter()
    result = run_dataset(ds, cfg, out, progress=sys.stderr.isatty())
    seconds = time.perf_counter() - t
    rows = list(csv.DictReader(open(out / "updates.csv")))
    ms = np.array([float(r["update_ms"]) for r in rows])
    first_pass_end = ds.stamps[len(dataset) - 1]
    with MapStore(out / "map.db") as store:
        stats = {n.id: store.statistics(n.id) for n in store.nodes(limit=None)}
        loops = [(lk.from_id, lk.to_id) for lk in store.links()
                 if lk.type in (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE)]
        merges = [(lk.from_id, lk.to_id) for lk in store.links(type=LinkType.MERGED)]  # (survivor, merged keyframe)
    out_at, back_at = {}, {}
    for node, st in sorted(stats.items()):
        for n in st["memory"]["transferred"]:
            out_at.setdefault(n, node)
        for n in st["memory"]["retrieved"]:
            back_at[n] = node
    late = int(len(rows) * (passes - 2) / passes)  # keyframes of the last two passes
    late_ids = {int(r["keyframe"]) for r in rows[late:]}
    to_retrieved = [(a, b) for a, b in loops if b in late_ids and a in out_at and a in back_at]
    merged_late = [(a, b) for a, b in merges if b in late_ids]
    merged_to_retrieved = [(a, b) for a, b in merged_late if a in out_at and a in back_at]
    return {
        "keyframes_first_pass": sum(float(r["stamp"]) <= first_pass_end and r["merged"] == "0" for r in rows),
        "keyframes": sum(r["merged"] == "0" for r in rows), "merged": sum(r["merged"] != "0" for r in rows),
        "wm_max": max(int(r["wm"]) for r in rows), "ltm_end": int(rows[-1]["ltm"]),
        "transferred": sum(int(r["transferred"]) for r in rows), "retrieved": sum(int(r["retrieved"]) for r in rows),
        "early": ms[100:300], "last": ms[-200:], "loops": len(loops), "loops_late_to_retrieved": len(to_retrieved),
        "merged_late": len(merged_late), "merged_late_to_retrieved": len(merged_to_retrieved),
        "ate": evaluate(ds.ground_truth, result.trajectory).ate_rmse, "seconds": seconds, "frames": len(ds),
        "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def main() -> int:
    default = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data")) / "7scenes_redkitchen"
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", nargs="?", default=str(default))
    ap.add_argument("--passes", type=int, default=10)
    ap.add_argument("--max-wm", type=int, default=100)
    ap.add_argument("--only", choices=["bounded", "unbounded"])
    ap.add_argument("--out", default="out/bench_memory")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override (repeatable)")
    args = ap.parse_args()
    overrides = parse_sets(args.set)
    dataset = open_dataset(args.dataset)
    results = {}
    for name, limit in (("bounded", args.max_wm), ("unbounded", 0)):
        if args.only and args.only != name:
            continue
        r = results[name] = run(dataset, args.passes, limit, Path(args.out) / name, overrides)
        e, last = r["early"], r["last"]
        print(f"{name} (memory.max_wm_nodes={limit}): {r['frames']} frames in {r['seconds']:.0f} s, map nodes "
              f"{r['keyframes_first_pass']} after pass 1, {r['keyframes']} after {args.passes} "
              f"({r['keyframes'] / max(r['keyframes_first_pass'], 1):.2f}x; {r['merged']} keyframes merged); "
              f"WM max {r['wm_max']}, LTM at the end {r['ltm_end']}; {r['transferred']} transferred, "
              f"{r['retrieved']} retrieved")
        print(f"  map update median / p99: keyframes 100-300 {np.median(e):.0f} / {np.percentile(e, 99):.0f} ms, "
              f"last 200 {np.median(last):.0f} / {np.percentile(last, 99):.0f} ms "
              f"(p99 ratio {np.percentile(last, 99) / np.percentile(e, 99):.2f})")
        print(f"  loop links {r['loops']}; in the last two passes to nodes retrieved from LTM: "
              f"{r['loops_late_to_retrieved']}; keyframes merged there {r['merged_late']}, into nodes retrieved from "
              f"LTM {r['merged_late_to_retrieved']}; ATE {r['ate'] * 100:.2f} cm; peak RSS {r['rss_mb']:.0f} MB")
    if len(results) == 2:
        print(f"ATE bounded / unbounded: {results['bounded']['ate'] / results['unbounded']['ate']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
