"""A long synthetic patrol (issue 11): tens of thousands of keyframes with memory management on
(rehearsal + bounded working memory) and off (unbounded WM, no rehearsal).

    python bench/bench_long_run.py [--keyframes 20000] [--off-keyframes 2000] [--only on|off]
                                   [--path loop] [--rate 3] [--width 320 --height 240]
                                   [--set memory.max_wm_nodes=100 ...] [--off-set KEY=VALUE ...]

A closed synthetic path played back and forth (`Passes`) at a frame rate low enough that
nearly every frame is a keyframe (RGBD/LinearUpdate 0.1 m: the "loop" path walks 0.12 m per
frame at 3 Hz), through one pipeline with the map update inline (as `mnemoslam run`), driven
frame by frame here rather than through `run_dataset` so that nothing is kept per frame but a
few numbers (RSS must not grow because of the bench) and the run can stop at exactly
`--keyframes` keyframes. Per keyframe: the map update's time (its statistics, the columns of
`updates.csv`); every `--rss-every` frames: RSS (/proc/self/statm).

"on" runs with `memory.rehearsal=true memory.max_wm_nodes=100` plus `--set`; "off" with
`memory.rehearsal=false memory.max_wm_nodes=0` plus `--off-set`. The off run stops at
`--off-keyframes` (default 2000): it only has
to show that without memory management the update is measurably slower at the end, so its
last window is compared with the on run's update times at the same keyframe indices (and with
the on run's own end). Each run is its own child process (its RSS is its own), writing
`--out/NAME/updates.csv` and `result.json`; `--only off` compares with an earlier on run in
the same `--out`.

Windows (the done-when of issue 11): update p99 over keyframes 1,000-2,000 against the last
1,000, RSS slope (MB per 1,000 keyframes, least squares) after the warm-up (keyframe 2,000).
A run shorter than 3,000 keyframes scales all three by keyframes / 3,000 (said in the output).
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets.passes import Passes  # noqa: E402
from mnemoslam.client.kernel.frames import DatasetError  # noqa: E402
from mnemoslam.client.kernel.geometry import invert  # noqa: E402
from mnemoslam.client.synthetic import SyntheticDataset  # noqa: E402
from mnemoslam.service.builder import build_pipeline  # noqa: E402
from mnemoslam.service.config import load_config, merge_overrides, parse_sets  # noqa: E402
from mnemoslam.service.runner import UPDATE_COLUMNS, UPDATE_STEPS, _frames, update_row  # noqa: E402
from mnemoslam.storage import MapStore  # noqa: E402

ON_DEFAULTS = ("memory.rehearsal=true", "memory.max_wm_nodes=100")
OFF_DEFAULTS = ("memory.rehearsal=false", "memory.max_wm_nodes=0", "memory.time_threshold_ms=0")
EARLY, LAST, FULL_WINDOWS = (1000, 2000), 1000, 3000  # keyframes 1,000-2,000 vs the last 1,000
PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE / 2**20


def windows(n: int) -> tuple[tuple[int, int], int, float]:
    """(early window, last-window length, scale) for a run of n keyframes."""
    s = min(1.0, n / FULL_WINDOWS)
    return (round(EARLY[0] * s), round(EARLY[1] * s)), max(1, round(LAST * s)), s


def keyframes_per_pass(ds: SyntheticDataset, linear: float, angular: float) -> int:
    """Keyframes a pass takes if odometry were exact (the distance / angle rule on ground truth)."""
    poses, last, n = ds.ground_truth.poses, 0, 1
    for i in range(1, len(poses)):
        d = invert(poses[last]) @ poses[i]
        angle = math.acos(max(-1.0, min(1.0, (np.trace(d[:3, :3]) - 1) / 2)))
        if np.linalg.norm(d[:3, 3]) >= linear or angle >= angular:
            last, n = i, n + 1
    return n


def make_dataset(args, target: int, cfg) -> tuple[Passes, int]:
    fx = 525.0 * args.width / 640  # the default camera's field of view at any width
    base = SyntheticDataset(args.path, rate=args.rate, width=args.width, height=args.height, fx=fx,
                            noise=not args.no_noise, seed=args.seed)
    per_pass = keyframes_per_pass(base, cfg.keyframe.linear_update, cfg.keyframe.angular_update)
    passes = max(1, math.ceil(1.1 * target / max(per_pass - 1, 1)) + 1)  # a margin: the run stops at `target`
    return Passes(base, passes), per_pass


def run_one(name: str, args) -> dict:
    """One run in this process: write out/NAME/updates.csv and result.json, return the result."""
    sets = list(ON_DEFAULTS) + (args.set or []) if name == "on" else list(OFF_DEFAULTS) + (args.off_set or [])
    cfg = load_config(None, merge_overrides({}, parse_sets(sets)))
    target = args.keyframes if name == "on" else args.off_keyframes
    ds, per_pass = make_dataset(args, target, cfg)
    out = Path(args.out) / name
    out.mkdir(parents=True, exist_ok=True)
    db = out / "map.db"
    for p in (db, db.with_name("map.db-wal"), db.with_name("map.db-shm")):
        p.unlink(missing_ok=True)
    print(f"{name}: {' '.join(sets) or 'defaults'}; synthetic {args.path} at {args.rate:g} Hz, "
          f"{args.width}x{args.height}, noise {'off' if args.no_noise else 'on'}: ~{per_pass} keyframes per pass, "
          f"up to {ds.passes} passes ({len(ds)} frames) until {target} keyframes", flush=True)
    rss_every = args.rss_every or min(500, max(10, target // 20))  # >= 20 samples on a short run
    kf_ms, kf_wm, kf_merged, kf_frame = [], [], [], []
    rss = [(0, 0, rss_mb())]  # (frame, keyframes so far, MB)
    lost = frames = 0
    t0 = time.perf_counter()
    with MapStore(db) as store, open(out / "updates.csv", "w", newline="") as fcsv:
        w = csv.writer(fcsv)
        w.writerow(UPDATE_COLUMNS + tuple(f"{s}_ms" for s in UPDATE_STEPS))
        pipeline = build_pipeline(store, ds.name, ds.calibration, cfg)  # map update inline
        mapper = pipeline.mapper
        bar = tqdm(total=target, desc=f"{name} keyframes", unit="kf", disable=not sys.stderr.isatty(),
                   dynamic_ncols=True)
        gen = _frames(ds)
        for frame in gen:
            frames += 1
            if isinstance(frame, DatasetError):
                continue
            r = pipeline.process(frame)
            lost += r.status == "lost"
            if r.node_id is not None:
                st = mapper.statistics.get(r.node_id)  # inline: the update is done
                m, t = (st.memory, st.timings_ms) if st is not None else ({}, {})
                ms = sum(t.values()) if st is not None else float("nan")
                kf_ms.append(ms)
                kf_wm.append(m.get("wm", 0))
                kf_merged.append(bool(m.get("merged")))
                kf_frame.append(r.index)
                w.writerow(update_row(r.node_id, m, t))
                bar.update()
                if len(kf_ms) % 100 == 0:
                    bar.set_postfix_str(f"wm {kf_wm[-1]} upd {np.median(kf_ms[-100:]):.0f} ms "
                                        f"rss {rss[-1][2]:.0f} MB", refresh=False)
            if frames % rss_every == 0:
                rss.append((frames, len(kf_ms), rss_mb()))
            if len(kf_ms) >= target:
                break
        gen.close()
        bar.close()
        rss.append((frames, len(kf_ms), rss_mb()))
        seconds = time.perf_counter() - t0
        loops = len(mapper.loops)
        pipeline.close()
    result = {"name": name, "sets": sets, "frames": frames, "lost": lost, "keyframes": len(kf_ms),
              "merged": int(sum(kf_merged)), "wm_max": max(kf_wm, default=0), "loops": loops,
              "seconds": seconds, "rss": rss, "update_ms": kf_ms, "keyframes_per_pass": per_pass}
    (out / "result.json").write_text(json.dumps(result) + "\n")
    return result


def report(r: dict, ref: dict | None = None) -> None:
    ms = np.asarray(r["update_ms"], dtype=float)
    n = len(ms)
    if n == 0:
        print(f"{r['name']}: no keyframes")
        return
    (e0, e1), last, scale = windows(n)
    note = f" (short run: windows scaled x{scale:.2f})" if scale < 1 else ""
    early, late = ms[e0:e1], ms[-last:]
    p_early, p_late = np.percentile(early, 99), np.percentile(late, 99)
    print(f"{r['name']}: {r['keyframes']} keyframes from {r['frames']} frames ({r['lost']} lost) in "
          f"{r['seconds']:.0f} s ({r['keyframes'] / r['seconds']:.1f} keyframes/s); map nodes "
          f"{r['keyframes'] - r['merged']} (not merged), {r['merged']} merged; WM max {r['wm_max']}; "
          f"{r['loops']} loop closures")
    goal = (" (done-when <= 1.2)", " (done-when <= 50)") if r["name"] == "on" else ("", "")
    print(f"  update median {np.median(ms):.1f} ms overall; p99 keyframes {e0:,}-{e1:,} {p_early:.1f} ms, "
          f"last {last:,} {p_late:.1f} ms: ratio {p_late / p_early:.2f}{goal[0]}; "
          f"median last {last:,} {np.median(late):.1f} ms{goal[1]}{note}")
    rss = np.asarray(r["rss"], dtype=float)  # frame, keyframes, MB
    warm = rss[rss[:, 1] >= e1]
    slope = (np.polyfit(warm[:, 1], warm[:, 2], 1)[0] * 1000 if len(warm) >= 3 and np.ptp(warm[:, 1]) > 0
             else float("nan"))
    at_warm = warm[0, 2] if len(warm) else float("nan")
    step = max(1, math.ceil(len(rss) / 16))
    shown = rss[::step].tolist() + ([rss[-1].tolist()] if (len(rss) - 1) % step else [])
    line = " ".join(f"{k / 1000:.1f}k:{mb:.0f}" if k >= 1000 else f"{k:.0f}:{mb:.0f}" for _, k, mb in shown)
    print(f"  RSS MB by keyframe: {line}")
    print(f"  RSS at warm-up (keyframe {e1:,}) {at_warm:.0f} MB, end {rss[-1, 2]:.0f} MB, "
          f"peak {rss[:, 2].max():.0f} MB; slope after warm-up {slope:+.2f} MB per 1,000 keyframes")
    if r["name"] == "off" and ref is not None:  # the off run against the on run at the same keyframe indices
        on = np.asarray(ref["update_ms"], dtype=float)
        if len(on) >= n:
            same = on[n - last:n]
            print(f"  vs on at the same keyframes {n - last:,}-{n:,}: median {np.median(late):.1f} / "
                  f"{np.median(same):.1f} ms = {np.median(late) / np.median(same):.2f}x, p99 "
                  f"{p_late:.1f} / {np.percentile(same, 99):.1f} ms; vs on's last {windows(len(on))[1]:,} "
                  f"(keyframe {len(on):,}): median {np.median(late) / np.median(on[-windows(len(on))[1]:]):.2f}x")
        else:
            print(f"  (the on run has {len(on)} keyframes, fewer than this run's {n}: no comparison)")
        print(f"  (the off run stops at {n:,} keyframes: it only has to show that without memory management "
              f"the update is slower at the same point; its own growth: median keyframes {e0:,}-{e1:,} "
              f"{np.median(early):.1f} ms -> last {last:,} {np.median(late):.1f} ms)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--keyframes", type=int, default=20000, help="keyframes of the on run (default 20000)")
    ap.add_argument("--off-keyframes", type=int, default=2000, help="keyframes of the off run (default 2000)")
    ap.add_argument("--only", choices=["on", "off"])
    ap.add_argument("--path", default="loop", help="closed synthetic path (loop, figure8)")
    ap.add_argument("--rate", type=float, default=3.0, help="frame rate, Hz (loop at 3 Hz: ~0.12 m per frame)")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--no-noise", action="store_true", help="clean depth and RGB")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rss-every", type=int, metavar="FRAMES",
                    help="RSS sample interval (default 500, less on short runs)")
    ap.add_argument("--out", default="out/bench_long_run")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE",
                    help=f"config override of the on run, after {' '.join(ON_DEFAULTS)} (repeatable)")
    ap.add_argument("--off-set", action="append", metavar="KEY=VALUE", help="config override of the off run")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    for s in (args.set, args.off_set):
        load_config(None, parse_sets(s))  # bad keys fail here, not in a child 30 minutes later
    if args.child:  # one run, in this process
        run_one(args.only, args)
        return 0
    t = time.perf_counter()
    results = {}
    for name in ("on", "off"):
        if args.only and args.only != name:
            continue
        subprocess.run([sys.executable, __file__, *sys.argv[1:], *([] if args.only else ["--only", name]), "--child"],
                       check=True)
        results[name] = json.loads((Path(args.out) / name / "result.json").read_text())
    if "off" in results and "on" not in results:
        on_file = Path(args.out) / "on" / "result.json"
        if on_file.exists():
            results["on"] = json.loads(on_file.read_text())
            print(f"(on run from an earlier invocation: {on_file})")
    print()
    for name in ("on", "off"):
        if name in results:
            report(results[name], results.get("on") if name == "off" else None)
    if "off" in results and "on" not in results:
        print("(no on run in --out to compare with)")
    print(f"bench: {time.perf_counter() - t:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
