"""Memory management on a long run: a sequence played back and forth (`--passes`), once with
working memory bounded (`memory.max_wm_nodes`) and once unbounded, and the sequence played
once (the single-pass ATE), offline with the map update inline (the same pipeline as
`mnemoslam run`).

    python bench/bench_memory.py [DATASET] [--passes 10] [--max-wm 100] [--only bounded|unbounded|single]
                                 [--set memory.rehearsal=true ...]
    python bench/bench_memory.py --issue23 [--only ...]   # the three runs of issue 23's done-when

DATASET defaults to $MNEMOSLAM_DATA/7scenes_redkitchen (`synthetic:fastrot` works too); `--set`
overrides config keys of every run. `--issue23` runs synthetic:fastrot x6 and TUM fr1/desk x6
with `--max-wm 100` and 7-Scenes x10 with 40, each bounded, unbounded and single-pass.
Prints per run: the map's nodes (keyframes not merged by rehearsal) after the first pass and
in all (their ratio), merged keyframes and those merged into a node in LTM (read from the
database, not retrieved), the largest WM, LTM at the end, transfers and retrievals (and both
per map update), the map update median and p99 per 200 keyframes, p99 over keyframes
100-300 and over the last 200 (and their ratio), loop links whose older node had been
transferred to LTM and retrieved before the link (in the last two passes), the ATE (and over
the single-pass ATE) and peak RSS. Each run's updates.csv is kept in --out; `--skip-done`
reads a run back from there instead of running it again.
"""
from __future__ import annotations

import argparse
import csv
import json
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
from mnemoslam.client.kernel.trajectory import read_tum  # noqa: E402
from mnemoslam.service.config import load_config, merge_overrides, parse_sets  # noqa: E402
from mnemoslam.service.evaluation import evaluate  # noqa: E402
from mnemoslam.service.runner import run_dataset  # noqa: E402
from mnemoslam.storage import LinkType, MapStore  # noqa: E402

DATA = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data"))
ISSUE23 = (("synthetic:fastrot", 6, 100), (str(DATA / "rgbd_dataset_freiburg1_desk"), 6, 100),
           (str(DATA / "7scenes_redkitchen"), 10, 40))
WINDOW = 200  # keyframes per row of the update-time table


def run(dataset, passes: int, max_wm: int, out: Path, overrides: dict, skip_done: bool = False) -> dict:
    ds = Passes(dataset, passes)
    cfg = load_config(None, merge_overrides(overrides, {"memory": {"max_wm_nodes": max_wm}}))
    t = time.perf_counter()
    if skip_done and (out / "result.json").exists():
        saved = json.loads((out / "result.json").read_text())
        trajectory, seconds = read_tum(out / "trajectory.tum"), saved["seconds"]
    else:
        trajectory = run_dataset(ds, cfg, out, progress=sys.stderr.isatty()).trajectory
        seconds = time.perf_counter() - t
        (out / "result.json").write_text(json.dumps({"seconds": seconds}))
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
        if not st:
            continue
        for n in st["memory"]["transferred"]:
            out_at.setdefault(n, node)
        for n in st["memory"]["retrieved"]:
            back_at[n] = node
    merged_in_ltm = sum(bool(st and st.get("rehearsal", {}).get("ltm")) and st["rehearsal"].get("decision") == "merged"
                        for st in stats.values())
    late = int(len(rows) * (passes - 2) / passes)  # keyframes of the last two passes
    late_ids = {int(r["keyframe"]) for r in rows[late:]}
    to_retrieved = [(a, b) for a, b in loops if b in late_ids and a in out_at and a in back_at]
    merged_late = [(a, b) for a, b in merges if b in late_ids]
    merged_to_retrieved = [(a, b) for a, b in merged_late if a in out_at and a in back_at]
    windows = [(k, ms[k:k + WINDOW]) for k in range(0, len(ms), WINDOW)]
    return {
        "keyframes_first_pass": sum(float(r["stamp"]) <= first_pass_end and r["merged"] == "0" for r in rows),
        "keyframes": sum(r["merged"] == "0" for r in rows), "merged": sum(r["merged"] != "0" for r in rows),
        "merged_in_ltm": merged_in_ltm, "updates": len(rows),
        "wm_max": max(int(r["wm"]) for r in rows), "ltm_end": int(rows[-1]["ltm"]),
        "transferred": sum(int(r["transferred"]) for r in rows), "retrieved": sum(int(r["retrieved"]) for r in rows),
        "median": float(np.median(ms)), "early": ms[100:300], "last": ms[-200:], "windows": windows,
        "loops": len(loops), "loops_late_to_retrieved": len(to_retrieved),
        "merged_late": len(merged_late), "merged_late_to_retrieved": len(merged_to_retrieved),
        "ate": evaluate(ds.ground_truth, trajectory).ate_rmse, "seconds": seconds, "frames": len(ds),
        "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def report(name: str, limit: int, passes: int, r: dict, single_ate: float | None) -> None:
    e, last = r["early"], r["last"]
    moves = (r["transferred"] + r["retrieved"]) / max(r["updates"], 1)
    print(f"{name} (memory.max_wm_nodes={limit}, {passes} passes): {r['frames']} frames, {r['updates']} map updates "
          f"in {r['seconds']:.0f} s; map nodes {r['keyframes_first_pass']} after pass 1, {r['keyframes']} at the end "
          f"({r['keyframes'] / max(r['keyframes_first_pass'], 1):.2f}x; {r['merged']} keyframes merged, "
          f"{r['merged_in_ltm']} of them into a node in LTM); WM max {r['wm_max']}, LTM at the end {r['ltm_end']}")
    print(f"  {r['transferred']} transferred, {r['retrieved']} retrieved: {moves:.2f} per update")
    print(f"  map update median {r['median']:.1f} ms; p99 keyframes 100-300 {np.percentile(e, 99):.0f} ms, "
          f"last 200 {np.percentile(last, 99):.0f} ms (ratio {np.percentile(last, 99) / np.percentile(e, 99):.2f})")
    print("  per 200 keyframes, median / p99 ms: " + ", ".join(
        f"{k}: {np.median(w):.0f} / {np.percentile(w, 99):.0f}" for k, w in r["windows"] if len(w) >= 20))
    ate = f"ATE {r['ate'] * 100:.2f} cm"
    if single_ate:
        ate += f" ({r['ate'] / single_ate:.2f}x the single pass's {single_ate * 100:.2f} cm)"
    print(f"  loop links {r['loops']}; in the last two passes to nodes retrieved from LTM: "
          f"{r['loops_late_to_retrieved']}; keyframes merged there {r['merged_late']}, into nodes retrieved from "
          f"LTM {r['merged_late_to_retrieved']}; {ate}; peak RSS {r['rss_mb']:.0f} MB")


def bench(path: str, passes: int, max_wm: int, out: Path, overrides: dict, only, skip_done: bool) -> None:
    dataset = open_dataset(path)
    results, single = {}, None
    if only in (None, "single"):
        single = run(dataset, 1, 0, out / "single", overrides, skip_done)
        print(f"{dataset.name} single pass: {single['updates']} map updates, {single['keyframes']} nodes, "
              f"ATE {single['ate'] * 100:.2f} cm")
    elif (out / "single" / "updates.csv").exists():
        single = run(dataset, 1, 0, out / "single", overrides, True)
    for name, limit in (("bounded", max_wm), ("unbounded", 0)):
        if only is not None and only != name:
            if not (skip_done and (out / name / "result.json").exists()):
                continue
        r = results[name] = run(dataset, passes, limit, out / name, overrides, skip_done)
        report(f"{dataset.name} {name}", limit, passes, r, single["ate"] if single else None)
    if len(results) == 2:
        print(f"ATE bounded / unbounded: {results['bounded']['ate'] / results['unbounded']['ate']:.3f}")
    sys.stdout.flush()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", nargs="?", default=str(DATA / "7scenes_redkitchen"))
    ap.add_argument("--passes", type=int, default=10)
    ap.add_argument("--max-wm", type=int, default=100)
    ap.add_argument("--issue23", action="store_true",
                    help="issue 23's three sequences (DATASET, --passes, --max-wm ignored)")
    ap.add_argument("--only", choices=["bounded", "unbounded", "single"])
    ap.add_argument("--skip-done", action="store_true", help="read runs already in --out instead of running them")
    ap.add_argument("--out", default="out/bench_memory")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override (repeatable)")
    args = ap.parse_args()
    overrides = parse_sets(args.set)
    jobs = ISSUE23 if args.issue23 else ((args.dataset, args.passes, args.max_wm),)
    for path, passes, max_wm in jobs:
        out = Path(args.out)
        if args.issue23:
            out = out / Path(path.split(":")[-1]).name
        bench(path, passes, max_wm, out, overrides, args.only, args.skip_done)
    return 0


if __name__ == "__main__":
    sys.exit(main())
